#!/usr/bin/env bash
# ablate-paper on every GPU of one lent machine, as a user runs it (Ray places one job a GPU), started detached so
# that it outlives the device call that starts it; each stage below is one device call, sent straight after the
# last (an idle machine goes back after 30 s). Carry .gpu (GPU_WHEELS_SLIM=1 ../shared/tools/gpu-wheels.sh .gpu)
# and .gpuray (../shared/tools/ray-gpu-bundle.sh .gpuray). The runs start from a copy of the tree without its
# repository: name the commit sent, PIXELGRAD_COMMIT=<sha>, before launch (each run's git.txt records it).
# Usage, from the repo root:
#   PIXELGRAD_COMMIT=<sha> bash benchmarks/paper_session.sh launch NAME ABLATE_PAPER_ARGS...
#             install the wheels, copy the tree to /tmp/pgpaper, start `ablate-paper --out /tmp/paper/NAME ARGS` with
#             setsid; e.g. cartpole-swingup's added arms as docs/seeded ran them on one H200 (two populations of
#             5: state runs pack into populations of their own, never with pixel arms; --gpus-per-run 0.5 puts
#             both on the one GPU, state's 4.5 minutes beside full-hard's 16):
#             launch arms6cp --tasks cartpole-swingup --arms full-hard state --seeds 0 1 2 3 4 --iters 3000
#               --time-limit-min 24 --pack 5 --gpus-per-run 0.5 --no-progress
#               --set compile=true device=cuda eval-every=250 checkpoint-every=1000 video-every=0 cosine-every=100
#             (CUDA_VISIBLE_DEVICES=1,3 before it: Ray places the runs on those GPUs only). Wait for other
#             jobs inside a script, never with `pgrep -f PATTERN` in the device call's own command line: the
#             pattern matches that command line, and the wait never ends.
#   progress  the log's last lines, each run's status, iteration and GPU from sweep.json, and the GPUs' load
#   wait [S]  until ablate-paper has exited, at most S seconds (560), then progress
#   collect   every run folder thinned (metrics every 10th iteration, evaluations and the last kept; no
#             checkpoints), sweep.json, the logs and the report as $OUT/paper_NAME.tar.xz
set -u
OUT=${OUT:-/tmp/out}; mkdir -p "$OUT"
# each bundle into its own folder, once per machine: another session script's detached runs may import from /tmp/site
[ -f /tmp/site/.installed ] || { python3 -m pip install -q --no-index --no-deps --no-compile --upgrade --target /tmp/site \
  .gpu/*.whl >/dev/null 2>&1 && touch /tmp/site/.installed; } || { echo "wheel install failed"; exit 1; }
[ -f /tmp/siteray/.installed ] || { python3 -m pip install -q --no-index --no-deps --no-compile --upgrade \
  --target /tmp/siteray .gpuray/*.whl >/dev/null 2>&1 && touch /tmp/siteray/.installed; } || { echo "ray install failed"; exit 1; }
# the tree the runs import, apart from other session scripts' copies (/tmp/pg)
T=/tmp/pgpaper
export PYTHONPATH=/tmp/site:/tmp/siteray:$T PATH=/tmp/siteray/bin:/tmp/site/bin:$PATH PYTHONUNBUFFERED=1 MPLBACKEND=Agg
P=/tmp/paper; mkdir -p $P
case ${1:?stage} in
  launch)
    name=${2:?name}; shift 2
    rm -rf $T; mkdir -p $T
    cp -r ablations gradlab tasks diffrender vocabulary benchmarks docs pyproject.toml $T/
    echo "${PIXELGRAD_COMMIT:?name the commit of the tree sent: PIXELGRAD_COMMIT=<sha>}" > $P/$name.commit
    nvidia-smi --query-gpu=index,name,memory.total --format=csv > $P/$name.gpus 2>&1
    echo "$name" > $P/current
    (cd $T && setsid python3 -m ablations paper --out $P/$name "$@" > $P/$name.log 2>&1 < /dev/null &) > /dev/null 2>&1
    sleep 60; bash "$0" progress;;
  progress)
    name=$(cat $P/current); tail -n 5 $P/$name.log | cut -c1-300
    python3 - "$P/$name/sweep.json" <<'PY'
import json, sys
try:
    runs = json.load(open(sys.argv[1]))["runs"]
except (OSError, ValueError) as e:
    sys.exit(f"no sweep.json yet ({e})")
for run_id, r in sorted(runs.items()):
    gpus = ",".join(r.get("gpus") or []) or "-"
    print(f"{run_id:40s} {r['status']:8s} it {r.get('iteration')} return {r.get('latest_return')} "
          f"host {r.get('host')} GPU {gpus} attempts {r.get('attempts')}")
PY
    nvidia-smi --query-gpu=index,utilization.gpu,memory.used --format=csv 2>/dev/null;;
  wait)
    end=$((SECONDS + ${2:-560}))
    while [ $SECONDS -lt $end ] && pgrep -f "^python3 -m ablations paper" > /dev/null; do sleep 10; done
    bash "$0" progress;;
  collect)
    name=$(cat $P/current); rm -rf /tmp/thin; mkdir -p /tmp/thin/$name
    (cd $T && python3 benchmarks/run_progress.py "$P/$name" --thin "/tmp/thin/$name" --every 10 > /dev/null)
    for x in sweep.json logs report; do [ -e "$P/$name/$x" ] && cp -r "$P/$name/$x" "/tmp/thin/$name/"; done
    cp $P/$name.log $P/$name.commit $P/$name.gpus /tmp/thin/$name/ 2>/dev/null
    tar -C /tmp/thin -cJf "$OUT/paper_$name.tar.xz" $name; ls -la "$OUT";;
  *) echo "unknown stage $1: launch NAME ARGS..., progress, wait [S], collect"; exit 2;;
esac
