#!/usr/bin/env bash
# One GPU-machine session: install the carried wheels, then run the named stages, each under its own time
# limit, writing JSON under $OUT (the device tool brings $OUT back). Usage, from the repo root:
#   bash benchmarks/gpu_session.sh STAGE[:SECONDS] ...
# Stages: env, cuda-tests, sim, render, iter, iter-compiled, learn-cartpole, sweep, table1.
set -u
OUT=${OUT:-/tmp/out}; mkdir -p "$OUT"
python3 -m pip install -q --no-index --no-deps --no-compile --upgrade --target /tmp/site .gpu/*.whl >/dev/null 2>&1 \
  || { echo "wheel install failed"; exit 1; }
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1 MPLBACKEND=Agg
run() { local secs=$1; shift; echo "=== $* (limit ${secs}s)"; timeout "$secs" "$@" 2>&1 | tail -n 40; }
for spec in "$@"; do
  stage=${spec%%:*}; secs=${spec#*:}; [ "$secs" = "$spec" ] && secs=300
  case $stage in
    env) nvidia-smi --query-gpu=name,driver_version,memory.total,clocks.sm --format=csv
         python3 -c "import torch, mujoco, pytorch_kinematics, trimesh, tyro; print(torch.__version__, torch.version.cuda, mujoco.__version__)";;
    cuda-tests) run "$secs" python3 -m pytest tests/test_cuda.py tests/diffrender -q -x -m "cuda" -p no:cacheprovider;;
    sim) run "$secs" python3 benchmarks/sim.py --device cuda --quick --out "$OUT/sim_quick.json";;
    render) run "$secs" python3 benchmarks/render.py --device cuda --quick --out "$OUT/render_quick.json";;
    iter) run "$secs" python3 benchmarks/iteration.py --device cuda --warmup 1 --iters 3 --out "$OUT/iter_eager.json" \
            --tasks ${TASKS:-cartpole hopper ant humanoid};;
    iter-compiled) run "$secs" python3 benchmarks/iteration.py --device cuda --compile --warmup 3 --iters 4 \
            --out "$OUT/iter_compiled.json" --tasks ${TASKS:-cartpole hopper ant humanoid};;
    *) echo "unknown stage $stage";;
  esac
done
ls -la "$OUT"
