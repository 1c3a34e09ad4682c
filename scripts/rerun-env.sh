#!/usr/bin/env bash
# The run recorder's packages in their own virtual environment (rerun-sdk 0.41 needs numpy >= 2,
# the openpi peers pin numpy 1.26.4):
#   rerun-sdk 0.41.0   writes the recording (tools/python/chunkrt_record.py), reads it back (the
#                      test) and is the viewer: `PREFIX/venv/bin/rerun run.rrd`
#   iceoryx2 0.10.0    chunkrt's IPC
#
#   bash scripts/rerun-env.sh [PREFIX]     # default PREFIX: ~/.cache/chunkrt-rerun
#
# Makes PREFIX/venv (idempotent), checks that the packages import, and prints the interpreter the
# tests and `chunkrt demo --record` use (CHUNKRT_RERUN_PYTHON).
set -euo pipefail
prefix=${1:-${CHUNKRT_RERUN_PREFIX:-$HOME/.cache/chunkrt-rerun}}
venv=$prefix/venv
py=$venv/bin/python
pins=('rerun-sdk==0.41.0' 'iceoryx2==0.10.0')

if [ ! -x "$py" ]; then
  echo "rerun-env: creating $venv" >&2
  python3 -m venv "$venv"
fi
"$py" -m pip install --quiet --disable-pip-version-check "${pins[@]}" \
  || { echo "rerun-env: pip could not install ${pins[*]} into $venv" >&2; exit 1; }
"$py" -c 'import rerun, iceoryx2, numpy, pyarrow; assert rerun.__version__ == "0.41.0", rerun.__version__' \
  || { echo "rerun-env: the packages in $venv do not import" >&2; exit 1; }
echo "CHUNKRT_RERUN_PYTHON=$py"
