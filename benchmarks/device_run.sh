#!/usr/bin/env bash
# Issue 35's GPU measurements on a lent CUDA machine, as one command from the repository root:
#   benchmarks/device_run.sh DATA OUT [python -m benchmarks.device_run options...]
# DATA holds data/sim_pick_place_small and robots/ (a copy of ../shared's); the machine has torch,
# CUDA and most packages but no network: the rest come as wheels in .whl/ (see the README's Device
# section for the download command). gsplat's CUDA extension is built once (OUT/gsplat_csrc.so) or
# taken from DATA/gsplat_csrc.so when a run before built it. Results: OUT/device.json.
set -euo pipefail
DATA=$1
OUT=$2
shift 2
t0=$(date +%s)
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl
# manisplat from this tree, as installed (drivers/, recorder/, calib/ in the manisplat namespace):
# links in the machine's copy of the tree, not an install (pip there has no build dependencies)
for d in drivers recorder calib; do ln -sfn "../$d" "manisplat/$d"; done
export PYTHONPATH="$PWD:/tmp/site" PYTHONUNBUFFERED=1
echo "installed in $(( $(date +%s) - t0 )) s"
export TORCH_CUDA_ARCH_LIST="${TORCH_CUDA_ARCH_LIST:-9.0}" MAX_JOBS="${MAX_JOBS:-$(nproc)}"
# a module built earlier for another torch fails its import check: then it is built anew
if [ -f "$DATA/gsplat_csrc.so" ] && python3 -m benchmarks.build_gsplat "$DATA/gsplat_csrc.so" --install; then
  :
else
  python3 -m benchmarks.build_gsplat "$OUT/gsplat_csrc.so"
fi
cache=()
[ -f "$DATA/compile_cache.bin" ] && cache=(--compile-cache "$DATA/compile_cache.bin")
python3 -m benchmarks.device_run --data "$DATA" --out "$OUT" "${cache[@]}" "$@"
