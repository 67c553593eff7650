#!/usr/bin/env bash
set -uo pipefail
t0=$(date +%s)
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl
for d in drivers recorder calib; do ln -sfn "../$d" "manisplat/$d"; done
export PYTHONPATH="$PWD:/tmp/site" PYTHONUNBUFFERED=1 TORCH_CUDA_ARCH_LIST=9.0 MAX_JOBS=16
python3 -m benchmarks.build_gsplat /tmp/gsplat_csrc.so > "$OUT/build_log.txt" 2>&1
echo "built at $(( $(date +%s) - t0 )) s"
timeout 150 python3 -m pytest -q -p no:cacheprovider tests/reconstruct/test_device.py tests/splat/test_gsplat_backend.py -k "cuda_run or synchronise or oracle" > "$OUT/tests_log.txt" 2>&1
echo "tests rc $? at $(( $(date +%s) - t0 )) s"
grep -v DEBUG "$OUT/tests_log.txt" | tail -12
