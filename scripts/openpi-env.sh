#!/usr/bin/env bash
# A Python for the inference bench's same-run openpi baseline (scripts/openpi_worker.py).
#
#   bash scripts/openpi-env.sh OPENPI_DIR [PREFIX]
#
# OPENPI_DIR: an openpi checkout (or its src/ folder) whose `openpi.models_pytorch` imports without
# jax, e.g. a full openpi environment, or a tree with openpi's three jax-only config modules shimmed.
# Developed and measured against openpi commit 15a9616a00943ada6c20a0f158e3adb39df2ccac.
# PREFIX (default ~/.cache/chunkrt-openpi): a virtual environment with the versions openpi's
# uv.lock pins at that commit, from PyPI: torch 2.7.1, transformers 4.53.2, tokenizers 0.21.1,
# huggingface_hub 0.32.3 (plus numpy and safetensors). openpi's `transformers_replace` files are
# copied over that transformers, as openpi's README instructs. Nothing of openpi is vendored here.
# PyPI's torch 2.7.1 wheel for Linux is the CUDA build: the download is ~3 GB even for a CPU run.
#
# Prints the two variables the bench reads; then:
#   cargo bench --bench inference -- --openpi "$CHUNKRT_OPENPI"
# To compare both programs' AVX2 paths on an AVX-512 CPU, cap both:
#   CHUNKRT_CPU_ISA=avx2 ATEN_CPU_CAPABILITY=avx2 MKL_ENABLE_INSTRUCTIONS=AVX2 ONEDNN_MAX_CPU_ISA=AVX2 \
#     cargo bench --bench inference -- --openpi "$CHUNKRT_OPENPI"
set -euo pipefail

main() {
  local dir="${1:-}" prefix="${2:-$HOME/.cache/chunkrt-openpi}" src=""
  if [ -z "$dir" ]; then
    echo "usage: bash scripts/openpi-env.sh OPENPI_DIR [PREFIX]" >&2
    return 2
  fi
  for cand in "$dir" "$dir/src"; do
    if [ -f "$cand/openpi/models_pytorch/pi0_pytorch.py" ]; then src="$(cd "$cand" && pwd)"; fi
  done
  if [ -z "$src" ]; then
    echo "openpi-env: no openpi/models_pytorch/pi0_pytorch.py under $dir or $dir/src" >&2
    return 1
  fi
  if [ ! -x "$prefix/bin/python" ]; then
    echo "openpi-env: creating $prefix" >&2
    python3 -m venv "$prefix"
  fi
  "$prefix/bin/pip" install --disable-pip-version-check -q \
    'torch==2.7.1' 'transformers==4.53.2' 'tokenizers==0.21.1' 'huggingface_hub==0.32.3' \
    'numpy<2.3' safetensors >&2
  local site
  site="$("$prefix/bin/python" -c 'import transformers, os; print(os.path.dirname(transformers.__file__))')"
  cp -r "$src/openpi/models_pytorch/transformers_replace/"* "$site/"
  echo "openpi-env: torch $("$prefix/bin/python" -c 'import torch; print(torch.__version__)'), transformers_replace applied to $site" >&2
  echo "export CHUNKRT_OPENPI=$src"
  echo "export CHUNKRT_OPENPI_PYTHON=$prefix/bin/python"
}

main "$@"
