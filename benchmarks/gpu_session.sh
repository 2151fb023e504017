#!/usr/bin/env bash
# One GPU-machine session: install the carried wheels, then run the named stages, each under its own time
# limit, writing JSON under $OUT (the device tool brings $OUT back). Usage, from the repo root:
#   bash benchmarks/gpu_session.sh STAGE[:SECONDS] ...
# Budget the limits for cold compiles: a fresh machine compiles the ant's substep in ~115 s and the humanoid's
# in ~95 s (H100) before a stage prints its first row.
# Stages: env, nvdiffrast, anchor, cuda-tests, population, fused-tests, graph-test, sim, sim-variants, sim-par, config-replay,
# profile, render, render-fused, raytrace, iter, iter-compiled, iter-warp, startup, learn, paper, sweep, detach, progress,
# collect, sim-agreement (see each case below).
set -u
OUT=${OUT:-/tmp/out}; mkdir -p "$OUT"
# once per machine: a later call must not rewrite the packages under a detached run that imports from them
[ -f /tmp/site/.installed ] || { python3 -m pip install -q --no-index --no-deps --no-compile --upgrade --target /tmp/site \
  .gpu/*.whl >/dev/null 2>&1 && touch /tmp/site/.installed; } || { echo "wheel install failed"; exit 1; }
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1 MPLBACKEND=Agg
# Warp travels in two halves (the bundle alone is near the 64 MiB a call carries): a call carrying .gpuwarp1
# leaves its half in /tmp/w, the next call (while the machine is warm) carries .gpuwarp2 and unpacks both.
mkdir -p /tmp/w; cp .gpuwarp1/* .gpuwarp2/* /tmp/w/ 2>/dev/null
if [ ! -d /tmp/site/warp ] && [ -f /tmp/w/warppart.00 ] && [ -f /tmp/w/warppart.01 ]; then
  cat /tmp/w/warppart.0* | xz -dc | tar -x -C /tmp/site && echo "warp unpacked"
fi
# each run's whole output is kept under $OUT (log_N.txt): the reply's tail can cut a test summary off
nlog=0
run() { local secs=$1; shift; nlog=$((nlog + 1)); echo "=== $* (limit ${secs}s)"
  timeout "$secs" "$@" > "$OUT/log_$nlog.txt" 2>&1; local rc=$?; tail -n 40 "$OUT/log_$nlog.txt"
  echo "=== rc $rc ($OUT/log_$nlog.txt)"; }
for spec in "$@"; do
  stage=${spec%%:*}; secs=${spec#*:}; [ "$secs" = "$spec" ] && secs=300
  case $stage in
    env) nvidia-smi --query-gpu=name,driver_version,memory.total,clocks.sm --format=csv
         python3 -c "import torch, mujoco, pytorch_kinematics, trimesh, tyro; print(torch.__version__, torch.version.cuda, mujoco.__version__)";;
    nvdiffrast) # the renderer anchor (never vendored): source from .shared/nvdiffrast, built into /tmp/nvdr
       NVDR_SRC=$PWD/.shared/nvdiffrast source .shared/nvdiffrast-build.sh;;
    anchor) # ours (each raster model), the Warp ray tracer and nvdiffrast on one scene; silhouette IoU
       run "$secs" python3 benchmarks/anchor.py ${ANCHOR_ARGS:-} --out "$OUT/anchor.json";;
    cuda-tests) run "$secs" python3 -m pytest tests/test_cuda.py tests/test_cuda_population.py tests/gradlab/test_population_critic.py tests/diffrender -q -x \
           -m "cuda" -p no:cacheprovider;;
    population) # populations against separate processes (benchmarks/population.py); POP_ARGS: its options
       run "$secs" python3 benchmarks/population.py ${POP_ARGS:-} --out "$OUT/population.json";;
    sim) run "$secs" python3 benchmarks/sim.py --device cuda --quick --modes ${SIM_MODES:-eager compiled graph} \
           --out "$OUT/sim_quick.json";;
    profile) # kernels of the captured forward / backward graphs by category, and the encoder alone
       run "$secs" python3 benchmarks/profile_iteration.py --tasks ${TASKS:-ant} --modes ${MODES:-decoupled full} \
         --encoder --out "$OUT/profile.json";;
    render) run "$secs" python3 benchmarks/render.py --device cuda --quick --out "$OUT/render_quick.json";;
    fused-tests) run "$secs" python3 -m pytest tests/diffrender/test_fused.py tests/diffrender/test_fused_setup.py -q -x -m "slow or not slow" -p no:cacheprovider ${FUSED_K:+-k "$FUSED_K"};;
    render-fused) # the fused Triton backend: kernel shapes (FUSED_VARIANTS) and the tiled one at the target
       # point, then batch / resolution / faces sweeps on the fused one
       run "$secs" python3 benchmarks/render.py --device cuda --backends fused tiled --graphs \
         --fused-variants ${FUSED_VARIANTS:-4x64} ${RENDER_TARGET_ONLY:+--target-only} --out "$OUT/render_fused.json";;
    sim-variants) # inductor settings for the simulator: ant, 64 envs, graph mode, one process per setting
       # (SIM_VARIANTS="base combo_kernels=true,aggressive_fusion=true ..."; commas separate settings)
       for v in ${SIM_VARIANTS:-base}; do opts=""; [ "$v" != base ] && opts="--inductor ${v//,/ }"
         run "$secs" python3 benchmarks/sim.py --device cuda --tasks ${SIM_TASK:-ant} --num-envs ${SIM_ENVS:-64} \
           --modes graph --kernels $opts --out "$OUT/sim_${v//[=,]/_}.json"; done;;
    iter) run "$secs" python3 benchmarks/iteration.py --device cuda --warmup 1 --iters 3 --out "$OUT/iter_eager.json" \
            --tasks ${TASKS:-cartpole hopper ant humanoid};;
    iter-compiled) # ITER_ARGS adds flags, e.g. "--modes decoupled full blind --raster-model softmax hard" (every arm)
       run "$secs" python3 benchmarks/iteration.py --device cuda --compile --warmup 3 --iters 4 \
            --out "$OUT/iter_compiled.json" --tasks ${TASKS:-cartpole hopper ant humanoid} ${ITER_ARGS:-};;
    sim-par) # inductor settings and cases in concurrent processes that compile together and then time one at a
       # time (benchmarks/sim.py --gpu-lock); SIM_JOBS="task:envs:setting ..." (setting "base" or k=v,k=v; a job
       # may repeat). Every row records the kernel configs autotuning kept (--configs). Jobs share inductor's and
       # Triton's caches, so later jobs may reuse configs an earlier one chose; SIM_FRESH_CACHES=1 gives each job
       # its own, so that each autotunes on its own (how far the configs alone move the time: BENCHMARKS.md s. 3)
       rm -rf /tmp/sim.lock* /tmp/simpar; mkdir -p /tmp/simpar; jobs=(${SIM_JOBS:-ant:64:base}); n=0
       for j in "${jobs[@]}"; do IFS=: read -r t e v <<< "$j"; opts=""; [ "$v" != base ] && opts="--inductor ${v//,/ }"
         n=$((n + 1)); tag="${n}_${t}${e}_${v//[=,.]/_}"
         caches=(); [ "${SIM_FRESH_CACHES:-0}" = 1 ] && caches=(TORCHINDUCTOR_CACHE_DIR="/tmp/simpar/cache_$n/inductor" \
           TRITON_CACHE_DIR="/tmp/simpar/cache_$n/triton")
         env "${caches[@]}" timeout "$secs" python3 benchmarks/sim.py --device cuda --tasks "$t" --num-envs "$e" --modes graph \
           --kernels --configs $opts --gpu-lock /tmp/sim.lock --parties ${#jobs[@]} --out "/tmp/simpar/$tag.json" \
           > "/tmp/simpar/$tag.log" 2>&1 &
       done; wait; tail -n 2 /tmp/simpar/*.log
       python3 -c "import json,sys; json.dump([json.load(open(f)) for f in sys.argv[2:]], open(sys.argv[1], 'w'), indent=1)" \
         "$OUT/sim_par.json" /tmp/simpar/*.json;;
    config-replay) # after "sim-par" with SIM_FRESH_CACHES=1 in the same call: time the fastest and the slowest job
       # again, each alone on a warm copy of its own caches (so it reuses the configs it kept), and list the kernels
       # whose kept configs differ between the two (benchmarks/config_diff.py)
       read -r fast slow < <(python3 -c "import json,glob,re; r=[(json.load(open(f))['rows'][0], re.match(r'/tmp/simpar/(\d+)_', f).group(1)) for f in glob.glob('/tmp/simpar/*.json')]; r=[x for x in r if 'ms' in x[0]]; r.sort(key=lambda x: x[0]['ms']); print(r[0][1], r[-1][1])")
       for n in $fast $slow; do f=$(ls /tmp/simpar/${n}_*.json); t=$(python3 -c "import json; r=json.load(open('$f'))['rows'][0]; print(r['task'], r['num_envs'])")
         set -- $t; TORCHINDUCTOR_CACHE_DIR="/tmp/simpar/cache_$n/inductor" TRITON_CACHE_DIR="/tmp/simpar/cache_$n/triton" \
           run "$secs" python3 benchmarks/sim.py --device cuda --tasks "$1" --num-envs "$2" --modes graph --configs \
           --out "$OUT/config_replay_$n.json"; done
       python3 benchmarks/config_diff.py "/tmp/simpar/${fast}_"*.json "/tmp/simpar/${slow}_"*.json | head -n 80;;
    graph-test) run "$secs" python3 -m pytest tests/test_cuda.py -q -x -p no:cacheprovider -k "captured and cartpole";;
    learn) # LEARN="task:mode:seed[:flag=value,flag=value] ..." runs concurrently on the one GPU, each stopping
           # after LEARN_MIN minutes (LEARN_FLAGS: more ablate flags for all, e.g. --compile); the run folders
           # (without checkpoints) and ablate-plot's PNGs come back as one tarball.
       mkdir -p /tmp/runs
       for spec in ${LEARN:-cartpole:decoupled:0 cartpole:full:0}; do IFS=: read -r t m s x <<< "$spec"
         extra=(); tag=""; for kv in ${x//,/ }; do extra+=("--${kv%%=*}" "${kv#*=}"); tag="${tag}_${kv#*=}"; done
         name="${t}_${m}${tag}_seed${s}"
         python3 -m ablations ablate --task "$t" --mode "$m" --seed "$s" --device cuda --iters ${LEARN_ITERS:-4000} \
           --time-limit-min "${LEARN_MIN:-6}" --cosine-every ${LEARN_K:-10} --video-every 100000 --out /tmp/runs \
           --name "$name" --no-progress ${LEARN_FLAGS:---compile} "${extra[@]}" > "/tmp/runs/$name.log" 2>&1 &
       done; wait
       tail -n 3 /tmp/runs/*.log; python3 -m ablations plot /tmp/runs/*/ --out /tmp/runs/plots 2>&1 | tail -3
       tar -C /tmp/runs --exclude=checkpoints -czf "$OUT/runs.tgz" . ;;
    paper) # ablate-paper on this GPU (PAPER_ARGS: --tasks --arms --seeds --time-limit-min --gpus-per-run ...); the
       # sweep folder (PAPER_OUT, default /tmp/paper) outlives the call while the machine is warm, so a next call
       # resumes and extends it. A first sweep of the same grid with "--iters 3 --time-limit-min None" in another
       # folder compiles every graph once, so that the measured runs start from inductor's warm caches instead of
       # spending their wall-clock budgets compiling side by side. Its runs (without checkpoints) come back as
       # one tarball; the report is drawn on the CPU machine.
       [ -d .gpuray ] && python3 -m pip install -q --no-index --no-deps --no-compile --upgrade --target /tmp/site \
         .gpuray/*.whl >/dev/null 2>&1; export PATH=/tmp/site/bin:$PATH
       TORCHINDUCTOR_COMPILE_THREADS=4 timeout "$secs" python3 -m ablations.paper --out ${PAPER_OUT:-/tmp/paper} ${PAPER_ARGS:-} \
         --set device=cuda compile=true video-every=100000 ${PAPER_SET:-} --no-progress 2>&1 | tail -n 60
       # in parts of 15 MB: a file over 16 MiB does not come back from the GPU machine (cat paper.tgz.* | tar -xz)
       out=${PAPER_OUT:-/tmp/paper}; tar -C "$(dirname "$out")" --exclude=checkpoints -cz "$(basename "$out")" \
         | split -b 15M -d - "$OUT/paper.tgz.";;
    sim-agreement) # the Warp simulator's actor gradient against the PyTorch one's from shared run states
       # (benchmarks/precision.py --candidates fp32-warp-sim; needs the Warp bundle unpacked, see above)
       run "$secs" python3 benchmarks/precision.py --device cuda --compile --tasks ${TASKS:-hopper ant} \
         --modes ${MODES:-decoupled full} --candidates fp32 fp32-warp-sim --parts agreement --iters ${AGREE_ITERS:-200} \
         --out "$OUT/sim_agreement.json";;
    raytrace) # the Warp ray tracer's variants (refit vs trace, eager vs graph) on the ant, 20k and 100k faces
       run "$secs" python3 benchmarks/raytrace.py --device cuda ${RAYTRACE_ARGS:-} --out "$OUT/raytrace.json";;
    iter-warp) # decoupled iterations with the soft rasterizer's forward against the ray tracer, one process;
       # ITER_TAG names the output, ITER_ARGS adds flags (e.g. --extra-meshes 32 --extra-mesh-verts 1024)
       run "$secs" python3 benchmarks/iteration.py --device cuda --compile --tasks ${TASKS:-ant} --modes decoupled \
         --renderers soft warp --warmup 3 --iters 4 --probe-every 0 ${ITER_ARGS:-} --out "$OUT/iter_warp${ITER_TAG:-}.json";;
    startup) # time to the first compiled iteration, cold (empty compile cache) then warm, fresh processes; each
       # run's summary and stderr come back (STARTUP_LOGS=recompiles sets TORCH_LOGS for the runs)
       rm -rf /tmp/startup_work
       # (an empty TORCH_LOGS makes torch 2.11 fail at import, so it is set only when asked for)
       [ -n "${STARTUP_LOGS:-}" ] && export TORCH_LOGS=$STARTUP_LOGS
       run "$secs" python3 benchmarks/startup.py --device cuda --tasks ${TASKS:-ant} \
         --modes ${MODES:-decoupled} --num-envs 64 --work /tmp/startup_work --out "$OUT/startup.json" ${STARTUP_ARGS:-}
       [ -n "${STARTUP_LOGS:-}" ] && unset TORCH_LOGS
       tar -C /tmp/startup_work -czf "$OUT/startup_runs.tgz" --exclude=checkpoints runs;;
    sweep) # the paper-size memory sweep (eager: peak allocated memory is exact outside CUDA graphs);
       # SWEEP_RENDERER=warp sweeps decoupled rollouts rendered by the ray tracer (SWEEP_MODES=decoupled);
       # SWEEP_JOBS=N runs N points at once (memory stays exact, times share the GPU)
       r=${SWEEP_RENDERER:-soft}
       timeout "$secs" python3 -m ablations memory --task ${SWEEP_TASK:-ant} --modes ${SWEEP_MODES:-decoupled full} \
         --renderer "$r" --meshes ${SWEEP_MESHES:-0 16 64} --verts ${SWEEP_VERTS:-64 256 1024} --num-envs 64 --horizon 32 \
         --image-size 84 --warmup-iters 1 --iters 2 --device cuda --out "/tmp/sweep_$r" --no-progress --timeout-s ${SWEEP_POINT_S:-240} \
         --jobs ${SWEEP_JOBS:-1} \
         2>&1 | tail -n 15
       tar -C /tmp --exclude=logs -czf "$OUT/sweep_$r.tgz" "sweep_$r" ;;
    detach) # one ablate run or population in a new process session, which outlives this call and runs until the
       # machine goes back: DETACH_NAME its folder under /tmp/runs, DETACH_ARGS its flags, DETACH_GPU the GPU;
       # its output goes to /tmp/runs/DETACH_NAME.log. Follow with "progress" calls, end with "collect" well before
       # the machine's 30 minutes are up: it goes back then even in the middle of a call, and the runs with it.
       # It runs from its own copy of the packages, /tmp/tree_DETACH_NAME: the next call replaces the working tree,
       # and a run imports some modules late. DETACH_TREE (a tar of the packages, e.g. `git archive PIN ablations
       # gradlab tasks diffrender vocabulary docs/floors.json`, carried) runs that tree instead: a registered run's
       # pinned tree (docs/confirmatory/README.md).
       mkdir -p /tmp/runs; export PATH=/tmp/site/bin:$PATH; tree=/tmp/tree_${DETACH_NAME:?}; rm -rf "$tree"; mkdir -p "$tree"
       if [ -n "${DETACH_TREE:-}" ]; then tar -xf "$DETACH_TREE" -C "$tree" || { echo "cannot unpack $DETACH_TREE"; exit 1; }
       else cp -r ablations gradlab tasks diffrender vocabulary "$tree"/; mkdir -p "$tree/docs"; cp docs/floors.json "$tree/docs/"; fi
       (cd "$tree" && PYTHONPATH=/tmp/site:$tree CUDA_VISIBLE_DEVICES=${DETACH_GPU:-0} setsid nohup python3 -m ablations ablate \
         ${DETACH_ARGS:-} --device cuda --out /tmp/runs --name "$DETACH_NAME" --no-progress > "/tmp/runs/$DETACH_NAME.log" 2>&1 \
         < /dev/null &) > /dev/null 2>&1  # the backgrounded list's own shell would hold this call's output open
       echo "detached $DETACH_NAME on GPU ${DETACH_GPU:-0} from $tree (${DETACH_TREE:-the working tree packages})"
       python3 -c "import sys; sys.path.insert(0, '$tree'); from ablations.tree_hash import tree_hash; print('tree hash', tree_hash('$tree').value)";;
    progress) # where the detached runs stand (benchmarks/run_progress.py), waiting PROGRESS_WAIT seconds first
       sleep "${PROGRESS_WAIT:-0}"; python3 benchmarks/run_progress.py /tmp/runs
       nvidia-smi --query-gpu=index,utilization.gpu,memory.used --format=csv,noheader;;
    collect) # COLLECT_STOP=1 first stops the detached runs (SIGTERM: each writes its summary and checkpoint);
       # then their folders, thinned (every COLLECT_EVERY-th iteration, every probe and evaluation, no checkpoints),
       # and their logs come back as a tarball in parts of 15 MB (cat runs.tgz.* | tar -xz)
       # (the pattern is anchored to the runs' own command line: unanchored, it also matches the shell of a call
       # whose command text names it, and stops that call)
       # COLLECT_WAIT=N first gives them up to N seconds to finish on their own
       for _ in $(seq ${COLLECT_WAIT:-0}); do pgrep -f "^python3 -m ablations ablate" >/dev/null || break; sleep 1; done
       if [ "${COLLECT_STOP:-0}" = 1 ]; then pkill -TERM -f "^python3 -m ablations ablate"
         for _ in $(seq 120); do pgrep -f "^python3 -m ablations ablate" >/dev/null || break; sleep 1; done; fi
       rm -rf /tmp/keep; python3 benchmarks/run_progress.py /tmp/runs --thin /tmp/keep/runs --every ${COLLECT_EVERY:-10}
       cp /tmp/runs/*.log /tmp/keep/ 2>/dev/null
       tar -C /tmp/keep -cz . | split -b 15M -d - "$OUT/runs.tgz.";;
    *) echo "unknown stage $stage";;
  esac
done
ls -la "$OUT"
