#!/bin/bash
# The long runs of the downstream comparison (benchmarks/results/README.md, "Downstream comparison") as two queues,
# one per CPU core, each a list of idempotent steps that resume from their checkpoints: after an interruption run the
# same command again. From the repository root, on a machine of this kind (2 cores):
#   CORE=A nohup bash scripts/downstream_queue.sh > queue_A.log 2>&1 &
#   CORE=B nohup bash scripts/downstream_queue.sh > queue_B.log 2>&1 &
# RUNS (default ../runs) says where the run folders go; the simulated worlds go to data/ and the banks to banks/, the
# paths configs/experiment/*.yaml name (make them links to a larger disk if needed). Each queue waits for what the
# other one writes (the world, the banks, the varied world).
# Core A: the 10 % seeds 0 and 2, transfer seeds 0 and 2 and the transfer table, the generation table's banks, the
# random-P_u nets and bank (and that arm's seeds 0, 2), the 1 % seeds 0 and 2, SPVCNN seed 0. Core B: the 10 % seeds
# 1 and 3, transfer seed 1, the FPD extractor and the generation table's FRD/FPD scores, the 1 % nets and bank, the
# random-P_u arm's seed 1, the 1 % seed 1, SPVCNN seed 1. The 10 % table (4 seeds x 4 arms) comes first.
# PY (default python3) runs the benchmark scripts; REAL is the labelled real SemanticKITTI root of the transfer test.
set -euo pipefail
RUNS=${RUNS:-../runs}
DATA=data
BANKS=banks
PY=${PY:-python3}
REAL=${REAL:-../shared/data/real/semantickitti}
CORE=${CORE:?set CORE=A or CORE=B}
export OMP_NUM_THREADS=1
WAIT=${WAIT:-300}  # seconds between looks at what the other queue writes
MAIN=(sup-only mt mt+r2dm mt+u4d)

done_bank() {  # a bank whose `u4d generate` finished
  python3 -c "import json,sys; sys.exit(0 if json.load(open('$1/manifest.json')).get('complete') else 1)" 2>/dev/null
}
wait_bank() { while ! done_bank "$1"; do sleep "$WAIT"; done; }
wait_file() { while [ ! -f "$1" ]; do sleep "$WAIT"; done; }
resume_flag() { if ls "$1"/checkpoints/step_*.pt > /dev/null 2>&1; then echo --resume; fi; }
last_step() { tail -n 1 "$1/log.jsonl" 2>/dev/null | python3 -c "import sys,json; print(json.loads(sys.stdin.read() or '{}').get('step', 0))" 2>/dev/null || echo 0; }

world() {  # the simulated world the nets and segmentors train on (places 00-87) and are scored on (88-99)
  if [ ! -f "$DATA/sim_seg/done" ]; then
    u4d simulate --out "$DATA/sim_seg" --sequences 100 --frames 8 --seed 10 --config configs/sim/seg_rich.yaml
    touch "$DATA/sim_seg/done"
  fi
}
probs() {  # NAME SEGMENTOR: per-point probabilities of every training place (U4D's uncertainty)
  if [ ! -f "$DATA/$1/done" ]; then
    u4d seg-predict "$2" "$DATA/sim_seg" --out "$DATA/$1" --sequences 00-87 --no-progress
    touch "$DATA/$1/done"
  fi
}
stage() {  # RUN STAGE [overrides...]: one 64x1024 diffusion stage, the shipped nets' recipe (8000 steps)
  local run=$1 name=$2
  shift 2
  [ "$(last_step "$run")" = "8000" ] && return 0
  u4d train-diffusion configs/u4d/cpu_hdl64.yaml "stage=$name" "data_root=$DATA/sim_seg" "$@" sample_every=0 \
    --out "$run" --no-progress $(resume_flag "$run")
}
bank() {  # OUT MODE [overrides...]: 512 scans at 64x1024 (configs/u4d/generate_hdl64.yaml) with the mean start
  local out=$1 mode=$2
  shift 2
  done_bank "$out" || u4d generate configs/u4d/generate_hdl64.yaml --out "$out" "mode=$mode" num=512 \
    mean_start_below=-10 "$@" --no-progress
}
experiment() {  # CONFIG OUT SEED ARM...: arms of one seed (finished runs are skipped, started ones resume)
  local config=$1 out=$2 seed=$3
  shift 3
  u4d experiment "$config" "seeds=[$seed]" --arms "$@" --out "$out" --no-progress
}
exp10() { local s=$1; shift; experiment configs/experiment/downstream_10pct.yaml "$RUNS/downstream_10pct" "$s" "$@"; }
exp1() { local s=$1; shift; experiment configs/experiment/downstream_1pct.yaml "$RUNS/downstream_1pct" "$s" "$@"; }
spv() {
  local s=$1
  shift
  u4d experiment configs/experiment/downstream_10pct.yaml "seeds=[$s]" "backbones=[spvcnn]" --arms "$@" \
    --out "$RUNS/downstream_10pct" --no-progress
}
random_nets() {  # the selection ablation: P_u drawn at random, the same recipe and budget as the shipped nets
  for name in stage1 stage2; do
    stage "$RUNS/gen64_random/$name" "$name" uncertainty.strategy=random "probs_root=$DATA/sim_seg_probs"
  done
  bank "$BANKS/u4d_random_hdl64_ms" u4d "stage1=$RUNS/gen64_random/stage1" "stage2=$RUNS/gen64_random/stage2"
}
nets_1pct() {  # 1 % labels: the uncertainty segmentor is sup-only of the 1 % split (8 labelled scans)
  local seg=$RUNS/unc_seg_1pct
  if [ ! -f "$seg/model.pt" ]; then
    u4d seg-train configs/seg/cpu_semi.yaml mode=supervised "data.root=$DATA/sim_seg" data.split_mode=sequence \
      data.label_fraction=0.01 data.max_points=12000 optim.lr=0.01 loss.level=voxel optim.steps=1000 \
      semi.burn_in_steps=700 eval_every=1000 data.val_max_scans=24 checkpoint_every=100 threads=1 seed=0 \
      --out "$seg" --no-progress $(resume_flag "$seg")
  fi
  probs sim_seg_probs_1pct "$seg/model.pt"
  for name in stage1 stage2; do
    stage "$RUNS/gen64_1pct/$name" "$name" "probs_root=$DATA/sim_seg_probs_1pct"
  done
  bank "$BANKS/u4d_1pct_hdl64_ms" u4d "stage1=$RUNS/gen64_1pct/stage1" "stage2=$RUNS/gen64_1pct/stage2"
}
transfer() {  # SEED: sim-to-real before (seg_rich world) / after (varied world), scored on the real labelled scans
  local seed=$1
  for w in seg_rich varied; do
    local root=$DATA/sim_seg run=$RUNS/transfer/${w}_s$seed
    [ "$w" = varied ] && root=$DATA/sim_varied
    [ -f "$run/model.pt" ] || u4d seg-train configs/seg/cpu_minkunet.yaml "data.root=$root" optim.steps=1284 \
      optim.anneal_to=steps max_minutes=0 threads=1 "seed=$seed" --out "$run" --no-progress $(resume_flag "$run")
    [ -f "$run/eval_real.json" ] || { u4d seg-eval "$run/model.pt" "$REAL" --json --confusion-png \
      "$run/confusion_real.png" --png "$run/reliability_real.png" --no-progress > "$run/eval_real.json.tmp" &&
      mv "$run/eval_real.json.tmp" "$run/eval_real.json"; }
    [ -f "$run/eval_sim.json" ] || { u4d seg-eval "$run/model.pt" "$root" --sequences 88-99 --json --no-progress \
      > "$run/eval_sim.json.tmp" && mv "$run/eval_sim.json.tmp" "$run/eval_sim.json"; }
  done
}
transfer_table() {  # before / after over the seeds that finished
  "$PY" benchmarks/transfer_table.py --runs "$RUNS/transfer" --worlds seg_rich varied \
    --out benchmarks/results/sim_to_real_transfer
}
fpd_extractor() {  # the FPD extractor at 64x1024 on the training places (train-extractor resumes from its partial file)
  [ -f "$RUNS/ext64/fpd.pt" ] || u4d train-extractor fpd configs/extractor/sim_hdl64.yaml "data.root=$DATA/sim_seg" \
    "out_dir=$RUNS/ext64" train.checkpoint_every=50 --quiet
}
bench_generation() {  # OUT METRICS [flags...]: U4D vs baseline vs the held-out floor, 3 seeds, both samplers, mean start
  local out=$1 metrics=$2
  shift 2
  [ -f "$out" ] || "$PY" benchmarks/bench_generation.py --root "$DATA/sim_eval" --stage1 weights/u4d_stage1.pt \
    --stage2 weights/u4d_stage2.pt --baseline weights/baseline.pt --reference 00-11 --floor 12-23 --num 64 \
    --seeds 0 1 2 --samplers dpmpp2m-sde:20:6 ddpm:32:16 --metrics "$metrics" --mask-fraction 0.1 --device cpu \
    --mean-start-below -10 \
    --work "$RUNS/bench_gen64" "$@" --out "$out"
}
generation_banks() {  # the generation table's banks (kept under RUNS/bench_gen64) with the extractor-free metrics
  if [ ! -f "$DATA/sim_eval/done" ]; then
    u4d simulate --out "$DATA/sim_eval" --sequences 24 --frames 8 --seed 77 --config configs/sim/seg_rich.yaml
    touch "$DATA/sim_eval/done"
  fi
  bench_generation "$RUNS/bench_gen64/banks.json" jsd,mmd,points,rangejs,intensityjs
}
generation_table() {  # the same banks scored with FRD and FPD once the FPD extractor is trained
  wait_file "$RUNS/bench_gen64/banks.json"
  bench_generation benchmarks/results/generation_64x1024.json frd,fpd,jsd,mmd,points,rangejs,intensityjs \
    --extractor-frd weights/extractor_frd.pt --extractor-fpd "$RUNS/ext64/fpd.pt"
}
varied_world() {
  if [ ! -f "$DATA/sim_varied/done" ]; then
    u4d simulate --out "$DATA/sim_varied" --sequences 100 --frames 8 --seed 10 --config configs/sim/varied.yaml
    touch "$DATA/sim_varied/done"
  fi
}

if [ "$CORE" = A ]; then
  world
  probs sim_seg_probs weights/uncertainty_segmentor.pt
  bank "$BANKS/r2dm_hdl64_ms" baseline
  exp10 0 sup-only mt
  wait_bank "$BANKS/u4d_hdl64_ms"
  exp10 0 "${MAIN[@]}"
  exp10 2 "${MAIN[@]}"  # the 10 % table first: the comparison the project exists for
  varied_world
  transfer 0
  transfer 2
  wait_file "$RUNS/transfer/varied_s1/eval_sim.json"
  transfer_table
  generation_banks
  random_nets
  exp10 0 mt+u4d-random
  exp10 2 mt+u4d-random
  wait_bank "$BANKS/u4d_1pct_hdl64_ms"
  exp1 0 "${MAIN[@]}"
  exp1 2 "${MAIN[@]}"
  spv 0 "${MAIN[@]}"
else
  wait_file "$DATA/sim_seg/done"
  bank "$BANKS/u4d_hdl64_ms" u4d
  exp10 1 sup-only mt
  wait_bank "$BANKS/r2dm_hdl64_ms"
  exp10 1 "${MAIN[@]}"
  exp10 3 "${MAIN[@]}"
  wait_file "$DATA/sim_varied/done"
  transfer 1
  fpd_extractor
  generation_table
  nets_1pct
  wait_bank "$BANKS/u4d_random_hdl64_ms"
  exp10 1 mt+u4d-random
  exp1 1 "${MAIN[@]}"
  spv 1 "${MAIN[@]}"
fi
echo "queue $CORE done"
