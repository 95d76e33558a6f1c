#!/bin/bash
# The runs of the downstream comparison that remain (benchmarks/results/downstream/README.md) as two
# queues, one per CPU core. From the repository root, on a machine of this kind (2 cores):
#   CORE=A nohup bash scripts/downstream_queue.sh > queue_A.log 2>&1 &
#   CORE=B nohup bash scripts/downstream_queue.sh > queue_B.log 2>&1 &
# What survives a session is what is committed: every finished `u4d experiment` run leaves its record in
# benchmarks/results/downstream/records (configs/experiment/downstream_*.yaml, records_dir) and is not trained again,
# and a finished diffusion net is exported to weights/ (commit both). Run folders, the simulated world and the banks
# stay on the machine: a queue on a new machine writes the world again (2 min) and the banks an arm needs (about an
# hour each, from the nets in weights/), and a run cut off by the end of a session starts again from its last
# checkpoint only on the same machine. So the steps come in pieces that fit one session (about 2.8 hours per core):
#   1. the bank arms of the 10 % seeds (A: the R2DM-style bank, then mt+r2dm of seeds 2, 3, 0, 1; B: the U4D bank,
#      then mt+u4d of seeds 3, 2, 1, 0: each core needs only its own bank, so neither waits for the other's),
#   2. any 10 % sup-only / mt seed without a record,
#   3. the random-P_u nets (A: stage 1, B: stage 2; exported to weights/u4d_random_stage*.pt; 2.5 to 3.5 hours each
#      on one thread, the length of a session: start them first),
#   4. the random-P_u bank and its arm's seeds 0 and 1,
#   5. the 1 % uncertainty segmentor (B, while A writes the random-P_u bank), its probabilities and nets
#      (weights/*_1pct*.pt; A: stage 1, B: stage 2),
#   6. A: the 1 % bank, the 1 % seed 0, SPVCNN at 10 % seed 0; B: SPVCNN seed 1 (its stage 2 ends first), 1 % seeds 1, 2.
# Each queue waits for what the other one writes (the world, a bank). RUNS (default ../runs) says where run folders go;
# the world goes to data/ and the banks to banks/, the paths configs/experiment/*.yaml name: links to RUNS/data and
# RUNS/banks where the checkout has neither, so a fresh checkout on the same machine finds them again.
set -euo pipefail
RUNS=${RUNS:-../runs}
DATA=data
BANKS=banks
CORE=${CORE:?set CORE=A or CORE=B}
export OMP_NUM_THREADS=1
WAIT=${WAIT:-300}  # seconds between looks at what the other queue writes
MAIN=(sup-only mt mt+r2dm mt+u4d)

done_bank() {  # a bank whose `u4d generate` finished
  python3 -c "import json,sys; sys.exit(0 if json.load(open('$1/manifest.json')).get('complete') else 1)" 2>/dev/null
}
keep() {  # NAME: ./NAME links to RUNS/NAME unless it is there, so the world and banks outlive a new checkout
  mkdir -p "$RUNS/$1"
  [ -e "$1" ] || ln -sn "$(cd "$RUNS/$1" && pwd)" "$1" 2> /dev/null || [ -e "$1" ]  # the other core may link first
}
wait_bank() { while ! done_bank "$1"; do sleep "$WAIT"; done; }
wait_file() { while [ ! -f "$1" ]; do sleep "$WAIT"; done; }
resume_flag() { if ls "$1"/checkpoints/step_*.pt > /dev/null 2>&1; then echo --resume; fi; }
last_step() { tail -n 1 "$1/log.jsonl" 2>/dev/null | python3 -c "import sys,json; print(json.loads(sys.stdin.read() or '{}').get('step', 0))" 2>/dev/null || echo 0; }

world() {  # the simulated world the nets and segmentors train on (places 00-87) and are scored on (88-99)
  if [ ! -f "$DATA/sim_seg/done" ]; then
    # 164 places: 00-87 train, 88-99 held out, 100-163 the ceiling arm's real bank (configs/experiment/design_*.yaml)
    u4d simulate --out "$DATA/sim_seg" --sequences 164 --frames 8 --seed 10 --config configs/sim/seg_rich.yaml
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
RECORDS=benchmarks/results/downstream/records
recorded() {  # SETTING SEED ARM...: every named arm of that seed has a record (minkunet unless BACKBONE is set)
  local setting=$1 seed=$2
  shift 2
  for arm in "$@"; do [ -f "$RECORDS/$setting/$arm/${BACKBONE:-minkunet}/seed$seed.json" ] || return 1; done
}
export_net() {  # RUN FILE: a finished net's EMA weights into weights/ (then add its row to weights/README.md)
  [ -f "$2" ] || u4d export-weights "$1" --out "$2"
}
bank_arm() {  # ARM BANK MODE SEED...: one 10 % bank arm over seeds; this core writes its bank when a seed needs it
  local arm=$1 out=$2 mode=$3 seed
  shift 3
  for seed in "$@"; do
    recorded 10pct "$seed" "$arm" && continue
    bank "$out" "$mode"
    exp10 "$seed" "$arm"
  done
}
main_arms() {  # SEED: sup-only and mt of a 10 % seed
  recorded 10pct "$1" sup-only mt || exp10 "$1" sup-only mt
}
random_net() {  # STAGE: the selection ablation's net, P_u drawn at random, the shipped nets' recipe and budget
  local file=weights/u4d_random_$1.pt
  [ -f "$file" ] && return 0
  if [ "$CORE" = A ]; then probs sim_seg_probs weights/uncertainty_segmentor.pt; fi
  wait_file "$DATA/sim_seg_probs/done"
  stage "$RUNS/gen64_random/$1" "$1" uncertainty.strategy=random "probs_root=$DATA/sim_seg_probs"
  export_net "$RUNS/gen64_random/$1" "$file"
}
random_arm() {  # SEED: the random-P_u bank arm of a 10 % seed (the bank from the exported nets)
  recorded 10pct "$1" mt+u4d-random && return 0
  wait_file weights/u4d_random_stage1.pt
  wait_file weights/u4d_random_stage2.pt
  if [ "$CORE" = A ]; then
    bank "$BANKS/u4d_random_hdl64_ms" u4d net= stage1=weights/u4d_random_stage1.pt stage2=weights/u4d_random_stage2.pt
  fi
  wait_bank "$BANKS/u4d_random_hdl64_ms"
  exp10 "$1" mt+u4d-random
}
nets_1pct() {  # 1 % labels: the uncertainty segmentor is sup-only of the 1 % split (8 labelled scans); core B
  # trains it while core A writes the random-P_u bank, so neither core waits idle
  local seg=$RUNS/unc_seg_1pct file=weights/uncertainty_segmentor_1pct.pt
  if [ ! -f "$file" ]; then
    u4d seg-train configs/seg/cpu_semi.yaml mode=supervised "data.root=$DATA/sim_seg" data.split_mode=sequence \
      data.label_fraction=0.01 data.max_points=12000 optim.lr=0.01 loss.level=voxel optim.steps=1000 \
      semi.burn_in_steps=700 eval_every=1000 data.val_max_scans=24 checkpoint_every=100 threads=1 seed=0 \
      --out "$seg" --no-progress $(resume_flag "$seg")
    u4d export-weights "$seg" --out "$file" --int8
  fi
}
net_1pct() {  # STAGE: a U4D net on the 1 % segmentor's uncertainty
  local file=weights/u4d_1pct_$1.pt
  [ -f "$file" ] && return 0
  wait_file weights/uncertainty_segmentor_1pct.pt
  if [ "$CORE" = A ]; then probs sim_seg_probs_1pct weights/uncertainty_segmentor_1pct.pt; fi
  wait_file "$DATA/sim_seg_probs_1pct/done"
  stage "$RUNS/gen64_1pct/$1" "$1" "probs_root=$DATA/sim_seg_probs_1pct"
  export_net "$RUNS/gen64_1pct/$1" "$file"
}
arms_1pct() {  # SEED: the four 1 % arms (the U4D bank from the exported 1 % nets; the R2DM-style bank is the 10 % one)
  recorded 1pct "$1" "${MAIN[@]}" && return 0
  wait_file weights/u4d_1pct_stage1.pt
  wait_file weights/u4d_1pct_stage2.pt
  if [ "$CORE" = A ]; then
    bank "$BANKS/u4d_1pct_hdl64_ms" u4d net= stage1=weights/u4d_1pct_stage1.pt stage2=weights/u4d_1pct_stage2.pt
  else
    bank "$BANKS/r2dm_hdl64_ms" baseline
  fi
  wait_bank "$BANKS/u4d_1pct_hdl64_ms"
  wait_bank "$BANKS/r2dm_hdl64_ms"
  exp1 "$1" "${MAIN[@]}"
}
spv_arms() {  # SEED: SPVCNN-like at 10 %, the four arms
  BACKBONE=spvcnn recorded 10pct "$1" "${MAIN[@]}" && return 0
  if [ "$CORE" = A ]; then bank "$BANKS/r2dm_hdl64_ms" baseline; else bank "$BANKS/u4d_hdl64_ms" u4d; fi
  wait_bank "$BANKS/r2dm_hdl64_ms"
  wait_bank "$BANKS/u4d_hdl64_ms"
  spv "$1" "${MAIN[@]}"
}

keep "$DATA"
keep "$BANKS"
if [ "$CORE" = A ]; then
  world
  bank_arm mt+r2dm "$BANKS/r2dm_hdl64_ms" baseline 2 3 0 1
  main_arms 0
  main_arms 2
  random_net stage1
  random_arm 0
  net_1pct stage1
  arms_1pct 0
  spv_arms 0
else
  wait_file "$DATA/sim_seg/done"
  bank_arm mt+u4d "$BANKS/u4d_hdl64_ms" u4d 3 2 1 0
  main_arms 1
  main_arms 3
  random_net stage2
  nets_1pct
  random_arm 1
  net_1pct stage2
  spv_arms 1  # stage 2 ends before core A's stage 1 and 1 % bank: SPVCNN needs only the 10 % banks
  arms_1pct 1
  arms_1pct 2
fi
echo "queue $CORE done"
