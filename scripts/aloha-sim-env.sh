#!/usr/bin/env bash
# openpi's ALOHA sim example client (examples/aloha_sim of openpi, run unchanged against
# `chunkrt serve --openpi-config pi0_aloha_sim`): its own virtual environment with the versions
# openpi pins for it (examples/aloha_sim/requirements.txt at 15a9616: gym-aloha 0.1.1, mujoco 2.3.7,
# dm-control 1.0.14, gymnasium 1.0.0, ...) plus PyPI's openpi-client; MuJoCo renders headless
# through EGL (scripts/so101-env.sh installs Mesa's where it is missing).
#
#   bash scripts/aloha-sim-env.sh [PREFIX]     # default PREFIX: ~/.cache/chunkrt-aloha-sim
#
# Prints CHUNKRT_ALOHA_PYTHON=<the venv's python> at the end (idempotent: a working venv is kept).
set -euo pipefail
prefix=${1:-${CHUNKRT_ALOHA_PREFIX:-$HOME/.cache/chunkrt-aloha-sim}}
venv=$prefix/venv
py=$venv/bin/python
probe() {
  MUJOCO_GL=egl "$py" -c "import gym_aloha, gymnasium, openpi_client, tyro, imageio_ffmpeg
env = gymnasium.make('gym_aloha/AlohaTransferCube-v0', obs_type='pixels_agent_pos')
obs, _ = env.reset(seed=0)
assert obs['pixels']['top'].shape == (480, 640, 3), obs['pixels']['top'].shape
" >/dev/null 2>&1
}
if [ -x "$py" ] && probe; then
  echo "aloha-sim-env: $venv ready"
else
  echo "aloha-sim-env: creating $venv"
  mkdir -p "$prefix"
  python3 -m venv "$venv"
  "$py" -m pip install --quiet --disable-pip-version-check \
    'gym-aloha==0.1.1' 'gymnasium==1.0.0' 'mujoco==2.3.7' 'dm-control==1.0.14' 'dm-env==1.6' \
    'dm-tree==0.1.8' 'labmaze==1.0.6' 'numpy==1.26.4' 'imageio==2.36.1' 'imageio-ffmpeg==0.5.1' \
    'matplotlib==3.9.3' 'tyro==0.9.2' 'typing-extensions==4.12.2' 'msgpack==1.1.0' \
    'websockets==14.1' 'openpi-client==0.1.2' 'pyopengl==3.1.7' 'scipy==1.14.1' 'lxml==5.3.0' \
    'absl-py==2.1.0' 'protobuf==5.29.1' 'pillow==11.0.0' 'glfw==2.8.0'
  probe || { echo "aloha-sim-env: gym-aloha does not render here (MUJOCO_GL=egl)" >&2; exit 1; }
  echo "aloha-sim-env: $venv ready"
fi
echo "CHUNKRT_ALOHA_PYTHON=$py"
