#!/bin/bash
# The long runs of the 64x1024 generators (issue "Scans with walls"), on the recipe the pilots chose
# (scripts/generator_pilots.sh, benchmarks/results/generation/pilots.md): one U4D net for both stages and the
# R2DM-style baseline, the same net size, batch and step budget, the plain ε-loss (no min-SNR weighting), constant lr.
# Each run trains in segments of SEGMENT steps up to STEPS; after each segment its EMA weights are exported
# (RUNS/NAME/METHOD_milestones/step_N.pt), 16 scans generated (both stages 20 steps of DPM-Solver++(2M) SDE, the mean
# start) and scored by benchmarks/gates.py against held-out places, so the learning curve (FPD and the teacher's
# building share against the step) grows as it trains. Resumable; one core each:
#   METHOD=u4d nohup bash scripts/generator_final.sh > ../runs/final_u4d.log 2>&1 &
#   METHOD=baseline nohup bash scripts/generator_final.sh > ../runs/final_baseline.log 2>&1 &
# or both on one core, segment by segment, so that their budgets are equal whenever the queue stops:
#   METHOD=both nohup bash scripts/generator_final.sh > ../runs/final_both.log 2>&1 &
# NAME (default final): the folder under RUNS. EXTRA: more train-diffusion overrides, e.g. the data-scarce generators
# of the downstream experiment (trained on its 18 places only, the scarce segmentor's probabilities):
#   NAME=scarce STEPS=8000 EXTRA='sequences=["05","11",...] probs_root=data/scarce_probs' METHOD=both bash ...
# AE: latent diffusion (LiDM-style) on that range-image autoencoder (OUT/autoencoder.pt of u4d train-autoencoder):
# configs/u4d/latent_hdl64.yaml, runs in RUNS/latent/NAME, the gates with the real scans through AE beside them (the
# best a generator on AE can do):
#   AE=../runs/latent/ae16/autoencoder.pt NAME=ae16 METHOD=both STEPS=4000 SEGMENT=2000 bash scripts/generator_final.sh
# The two-level cascade (u4d_aug.cascade): both methods learn whole rings at a quarter of the columns (the layout),
# METHOD=detail trains the one detail net both share (milestones exported, no bank: it needs a layout), and DETAIL
# makes each milestone's 16 scans through that detail net at full width (cascade_bank_N, cascade_gates_N.json), or with
# DETAIL=nearest through no net (each layout column repeated 4 times), so a finished layout run re-run with DETAIL only
# adds its cascade banks:
#   LAYOUT="height=64 width=256 crop_width=0 net.attention=true net.attention_heads=4 batch_size=4"
#   NAME=cascade METHOD=both STEPS=6000 SEGMENT=2000 EXTRA="$LAYOUT" bash scripts/generator_final.sh
#   NAME=cascade METHOD=detail STEPS=4000 SEGMENT=2000 EXTRA="detail_stride=4 crop_width=256 crop_margin=16 \
#     net.attention=true net.attention_heads=4 batch_size=4" bash scripts/generator_final.sh
#   DETAIL=RUNS/cascade/detail_milestones/step_4000.pt NAME=cascade METHOD=both ... EXTRA="$LAYOUT" bash ...
set -euo pipefail
RUNS=${RUNS:-../runs}
NAME=${NAME:-final}
AE=${AE:-}
DETAIL=${DETAIL:-}
METHOD=${METHOD:?set METHOD=u4d, baseline, both or detail}
STEPS=${STEPS:-60000}
SEGMENT=${SEGMENT:-4000}
read -r -a extra <<< "${EXTRA:-}"
if [ "$METHOD" = both ]; then
  for ((target = SEGMENT; target <= STEPS; target += SEGMENT)); do
    for m in u4d baseline; do METHOD=$m STEPS=$target bash "$0"; done
  done
  exit 0
fi
export OMP_NUM_THREADS=1
if [ -n "$AE" ]; then
  F=$RUNS/latent/$NAME
  CONFIG=configs/u4d/latent_hdl64.yaml
  RECIPE=("autoencoder=$AE")
  COND_NOISE=0.1
  GATES=(--autoencoder "ae=$AE")
else
  F=$RUNS/$NAME
  CONFIG=configs/u4d/cpu_hdl64.yaml
  RECIPE=(data_root=data/sim_seg probs_root=data/sim_seg_probs sample_every=0 log_every=50 checkpoint_every=500
    keep_checkpoints=2 diffusion.min_snr_gamma=null)
  COND_NOISE=0.05
  GATES=()
fi

last_step() {  # the last logged step of run folder $1 (0 before its first log line)
  [ -f "$1/log.jsonl" ] || { echo 0; return; }
  tail -n 1 "$1/log.jsonl" | python3 -c "import sys,json; print(json.loads(sys.stdin.read() or '{}').get('step', 0))"
}
resume_flag() { if ls "$1"/checkpoints/step_*.pt > /dev/null 2>&1; then echo --resume; fi; }
run=$F/$METHOD
milestones=$F/${METHOD}_milestones
mkdir -p "$milestones"
if [ "$METHOD" = u4d ]; then
  stage=(stage=u4d "diffusion.cond_noise=$COND_NOISE")
elif [ "$METHOD" = detail ]; then
  stage=(stage=detail "diffusion.cond_noise=$COND_NOISE")
else
  stage=(stage=baseline)
fi
cascade=()
prefix=""
if [ -n "$DETAIL" ]; then
  cascade=("detail=$DETAIL")
  prefix=cascade_
fi
for ((target = SEGMENT; target <= STEPS; target += SEGMENT)); do
  weights=$milestones/step_$target.pt
  if [ "$(last_step "$run")" -lt "$target" ]; then
    u4d train-diffusion "$CONFIG" "steps=$target" "${RECIPE[@]}" "${stage[@]}" ${extra[@]+"${extra[@]}"} --out "$run" \
      --no-progress $(resume_flag "$run")
  fi
  [ -f "$weights" ] || { [ "$(last_step "$run")" = "$target" ] && u4d export-weights "$run" --out "$weights"; }
  [ "$METHOD" = detail ] && continue  # a detail net samples only given a layout (DETAIL= of the other methods)
  bank=$milestones/${prefix}bank_$target
  if ! python3 -c "import json,sys; sys.exit(0 if json.load(open('$bank/manifest.json')).get('complete') else 1)" 2>/dev/null; then
    if [ "$METHOD" = u4d ]; then
      u4d generate configs/u4d/generate_hdl64.yaml --out "$bank" mode=u4d "net=$weights" stage1= stage2= num=16 \
        batch_size=4 stage1_steps=20 ${cascade[@]+"${cascade[@]}"} --no-progress
    else
      u4d generate configs/u4d/generate_hdl64.yaml --out "$bank" mode=baseline "baseline=$weights" num=16 \
        batch_size=4 ${cascade[@]+"${cascade[@]}"} --no-progress
    fi
  fi
  gates=$milestones/${prefix}gates_$target.json
  [ -f "$gates" ] || "${PY:-python3}" benchmarks/gates.py --bank "${prefix}${METHOD}_$target=$bank" \
    ${GATES[@]+"${GATES[@]}"} --real data/sim_eval --real-sequences 00-11 --num 16 --work "$F/gates_work" \
    --out "$gates" > /dev/null
done
echo "$NAME $METHOD done"
