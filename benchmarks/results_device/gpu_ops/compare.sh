#!/usr/bin/env bash
# The device call of 2026-11-28 (run as `bash .devdata/compare.sh` from the repository root, carrying
# .whl (as docs/development.md lists, plus embreex), .devdata (sim_pick_place_small, robots/) and
# .before = `git archive da2bb31 manisplat drivers recorder calib pyproject.toml benchmarks`):
# the eager iteration after (this tree, commit 5ae40cb) and before (da2bb31), then the CUDA tests
set -uo pipefail
export PYTHONUNBUFFERED=1
O=$OUT; R=$PWD; t0=$(date +%s)
opts=(--steps iteration --episodes pp,sample --variants eager --pp-iters 600 --sample-iters 600 --steady-iters 100 --profile-iters 20 --cpu-iters 300 --budget-s 200)
timeout 240 bash benchmarks/device_run.sh .devdata "$O/after" "${opts[@]}" > "$O/after_log.txt" 2>&1
echo "after: rc $? at $(( $(date +%s) - t0 )) s"
[ -f "$O/after/gsplat_csrc.so" ] && mv "$O/after/gsplat_csrc.so" .devdata/
cd .before && ln -sfn ../.whl .whl && timeout 150 bash benchmarks/device_run.sh ../.devdata "$O/before" "${opts[@]}" > "$O/before_log.txt" 2>&1
echo "before: rc $? at $(( $(date +%s) - t0 )) s"
cd "$R"
timeout 170 bash benchmarks/device_run.sh .devdata "$O/tests" --steps tests --budget-s 60 > "$O/tests_run_log.txt" 2>&1
echo "tests: rc $? at $(( $(date +%s) - t0 )) s"
rm -f "$O"/*/gsplat_csrc.so
grep -h "ms_per_iter\|summary" "$O"/*/device.json | head -20
