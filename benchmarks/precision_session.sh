#!/usr/bin/env bash
# The encoder-precision evidence and the rasterizer's walk timings on one four-GPU machine (benchmarks/precision.py,
# docs/design.md "Numeric precision"), in stages, each a device call sent straight after the last. Carry .gpu
# (GPU_WHEELS_SLIM=1 ../shared/tools/gpu-wheels.sh .gpu) and .shared (git-ignored: nvdiffrast's source as
# .shared/nvdiffrast, `git archive 253ac4f csrc nvdiffrast` of the snapshot `fetch github:NVlabs/nvdiffrast` brings, and
# ../shared/tools/nvdiffrast-build.sh: the anchor, built there, never vendored). Usage, from the repo root:
# bash benchmarks/precision_session.sh STAGE (launch: PIXELGRAD_COMMIT=<sha> bash ...: the runs start from a copy of
# the tree without its repository, and each run's git.txt and every benchmark JSON record the commit named)
#   launch    install the carried wheels, copy the tree to /tmp/pg and start, detached (setsid), the seeded
#             comparison: hopper, 5 seeds, 2000 iterations, one population a GPU: fp32 decoupled (GPU 0), fp32
#             full (1), bf16 decoupled (2), bf16 full (3) (the same arm set at both precisions, so grouped kernels
#             round alike); then, detached too, on each decoupled population's GPU once it has ended: GPU 0 the
#             walk variants (diffrender.raster.fused.tuning: FWD_COMPACT, FWD_DEFER_SHADING, BWD_COMPACT) at 768
#             ant images, their CUDA tests, then anchor.py's timings of each beside nvdiffrast; GPU 2
#             profile_iteration.py at 768 environments (ant, decoupled and full, fp32 and bf16)
#   progress  the last line of every log
#   wait [S]  until every detached job has ended, at most S seconds (560), then progress
#   agreement on idle GPUs 2 and 3: the gradient agreement (cosines with float32) of hopper and ant
#   time      on idle GPUs, one process a GPU: precision.py's times of the ant (GPU 0); population.py at 1, 4 and
#             12 members: the ant at fp32 (1) and bf16 (2), the hopper at bf16 (3)
#   collect   the thinned run folders and every JSON and log as one tarball under $OUT
set -u
OUT=${OUT:-/tmp/out}; mkdir -p "$OUT"
[ -f /tmp/site/.installed ] || { python3 -m pip install -q --no-index --no-deps --no-compile --upgrade --target /tmp/site \
  .gpu/*.whl >/dev/null 2>&1 && touch /tmp/site/.installed; } || { echo "wheel install failed"; exit 1; }
export PYTHONPATH=/tmp/site:/tmp/pg PYTHONUNBUFFERED=1 MPLBACKEND=Agg
R=/tmp/pgruns; mkdir -p $R
# the commit launch was named, for the later stages' benchmarks
[ -z "${PIXELGRAD_COMMIT:-}" ] && [ -f $R/commit.txt ] && export PIXELGRAD_COMMIT=$(cat $R/commit.txt)
case ${1:?stage} in
  launch)
    rm -rf /tmp/pg; mkdir -p /tmp/pg; cp -r ablations gradlab tasks diffrender vocabulary benchmarks tests pyproject.toml /tmp/pg/
    cp -r .shared /tmp/pg/ 2>/dev/null; mkdir -p /tmp/pg/docs && cp docs/floors.json /tmp/pg/docs/
    echo "${PIXELGRAD_COMMIT:?name the commit of the tree sent: PIXELGRAD_COMMIT=<sha>}" > $R/commit.txt
    nvidia-smi --query-gpu=index,name,memory.total --format=csv > $R/gpus.txt
    common="--task hopper --seed 0 1 2 3 4 --iters 2000 --eval-every 250 --cosine-every 100 --compile --video-every 0
            --checkpoint-every 1000 --time-limit-min 21 --device cuda --no-progress --out $R"
    gpu=0
    for p in fp32 bf16; do for m in decoupled full; do
      (cd /tmp/pg && CUDA_VISIBLE_DEVICES=$gpu setsid python3 -m ablations ablate $common --mode $m --precision $p \
        --name hopper_${m}_$p > $R/hopper_${m}_$p.log 2>&1 < /dev/null &) > /dev/null 2>&1
      gpu=$((gpu + 1)); done; done
    (cd /tmp/pg && setsid bash "$PWD/benchmarks/precision_session.sh" after-populations > $R/after.log 2>&1 < /dev/null &) \
      > /dev/null 2>&1
    sleep 45; tail -n 3 $R/*.log;;
  after-populations)  # detached by launch: each decoupled population's GPU takes a timing job once it is free
    cd /tmp/pg
    ended() { ! pgrep -f "ablations ablate .*--name $1" > /dev/null; }
    sleep 30  # the populations' processes are up before anything waits on them
    (until ended hopper_decoupled_fp32; do sleep 5; done
     NVDR_SRC=/tmp/pg/.shared/nvdiffrast source .shared/nvdiffrast-build.sh > $R/nvdiffrast.log 2>&1 || true
     CUDA_VISIBLE_DEVICES=0 python3 -m pytest -q -p no:cacheprovider tests/diffrender/test_fused.py -k "compacted or variants" \
      > $R/time_walk_tests.log 2>&1
     CUDA_VISIBLE_DEVICES=0 python3 benchmarks/anchor.py --batch 768 --faces 0 --parts time --compile on --no-warp \
      --variants default FWD_COMPACT=1,FWD_SUB_BLOCK=16 FWD_COMPACT=1,FWD_SUB_BLOCK=8 FWD_DEFER_SHADING=1 \
      FWD_COMPACT=1,FWD_SUB_BLOCK=16,FWD_DEFER_SHADING=1 BWD_COMPACT=1,BWD_SUB_BLOCK=32 BWD_SUB_BLOCK=32 \
      FWD_COMPACT=1,FWD_SUB_BLOCK=16,FWD_MAXNREG=128 FWD_COMPACT=1,FWD_SUB_BLOCK=8,FWD_MAXNREG=128 \
      --out $R/anchor_walks_768.json > $R/time_walks.log 2>&1
     CUDA_VISIBLE_DEVICES=0 python3 benchmarks/anchor.py --batch 768 --faces 21000 --parts time --compile on --no-warp \
      --variants default FWD_COMPACT=1,FWD_SUB_BLOCK=16 BWD_COMPACT=1,BWD_SUB_BLOCK=32 \
      --out $R/anchor_walks_768_21k.json > $R/time_walks_21k.log 2>&1) &
    (until ended hopper_decoupled_bf16; do sleep 5; done
     CUDA_VISIBLE_DEVICES=2 python3 benchmarks/profile_iteration.py --tasks ant --modes decoupled full --num-envs 768 \
      --precision fp32 bf16 --encoder --out $R/profile_768.json > $R/time_profile.log 2>&1) &
    wait; echo "after-populations done";;
  progress)
    for f in $R/*.log; do echo "== $f"; tail -n 2 "$f" | cut -c1-300; done
    nvidia-smi --query-gpu=index,utilization.gpu,memory.used --format=csv;;
  agreement)
    cd /tmp/pg
    for t in hopper:2 ant:3; do
      CUDA_VISIBLE_DEVICES=${t#*:} python3 benchmarks/precision.py --device cuda --compile \
        --tasks ${t%%:*} --iters 200 --parts agreement --candidates fp32 tf32 bf16 \
        --out $R/precision_agreement_${t%%:*}.json > $R/agreement_${t%%:*}.log 2>&1 &
    done
    wait; tail -n 12 $R/agreement_*.log;;
  time)  # BENCHMARKS sections 7 and 8: one GPU a job, in one call
    cd /tmp/pg
    CUDA_VISIBLE_DEVICES=0 python3 benchmarks/precision.py --device cuda --compile --tasks ant --parts time \
      --candidates fp32 bf16 --out $R/precision_time_ant.json > $R/time_single.log 2>&1 &
    for job in 1:ant:fp32 2:ant:bf16 3:hopper:bf16; do IFS=: read -r gpu task prec <<< "$job"
      CUDA_VISIBLE_DEVICES=$gpu python3 benchmarks/population.py --tasks $task --members 1 4 12 --precision $prec \
        --out $R/population_${task}_$prec.json > $R/time_pop_${task}_$prec.log 2>&1 &
    done
    wait; tail -n 25 $R/time_*.log;;
  wait)  # until the populations and the timing jobs after them have ended, at most ${2:-560} s; then progress
    end=$((SECONDS + ${2:-560}))
    while [ $SECONDS -lt $end ] && \
          pgrep -f "ablations ablate .*--name hopper_[a-z]+_(fp32|bf16)|precision_session.sh after-populations" > /dev/null; do
      sleep 10; done
    bash "$0" progress;;
  collect)
    cd /tmp/pg && rm -rf /tmp/thin && python3 benchmarks/run_progress.py $R --thin /tmp/thin --every 10 > /dev/null
    cp $R/*.json $R/*.log $R/*.txt /tmp/thin/ 2>/dev/null
    tar -C /tmp -cJf "$OUT/precision_runs.tar.xz" thin; ls -la "$OUT";;
esac
