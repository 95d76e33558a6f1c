#!/bin/bash
# Pilots of the 64x1024 generator recipe (issue "Scans with walls"): each candidate trains at one small, equal budget
# (BUDGET steps x batch 4 of the base-16 net; a wider net gets fewer steps, in proportion to its measured step cost;
# the one-net pilots put noise of std up to 0.05 on stage 2's condition), then writes a bank of 16 scans and is scored
# on held-out scans: one denoising call by log-SNR (benchmarks/diagnostics/diag_denoise.py) and, where benchmarks/gates.py exists, the gates (teacher kept / building share, BEV
# points per cell, roughness, FPD). Two queues, one per core, resumable (a killed pilot resumes from its checkpoint):
#   CORE=A nohup bash scripts/generator_pilots.sh > ../runs/pilots_A.log 2>&1 &
#   CORE=B nohup bash scripts/generator_pilots.sh > ../runs/pilots_B.log 2>&1 &
# ROUND=2: the second round (the min-SNR weighting), after the first.
# RUNS (default ../runs) holds the run folders; the world is data/sim_seg (places 00-87 train) with the uncertainty
# segmentor's probabilities data/sim_seg_probs, the held-out scans data/sim_eval (+ data/sim_eval_probs).
set -euo pipefail
RUNS=${RUNS:-../runs}
P=$RUNS/pilots
CORE=${CORE:?set CORE=A or CORE=B}
BUDGET=${BUDGET:-1500}
export OMP_NUM_THREADS=1
PRESET=configs/u4d/cpu_hdl64.yaml
COMMON=(data_root=data/sim_seg probs_root=data/sim_seg_probs sample_every=0 log_every=50 checkpoint_every=250
  ema_decay=0.998)
COSINE=(optim.schedule=cosine optim.min_lr_ratio=0.05)
WIDE=(net.base_channels=24 net.attention=true net.attention_heads=4)

last_step() { tail -n 1 "$1/log.jsonl" 2>/dev/null | python3 -c "import sys,json; print(json.loads(sys.stdin.read() or '{}').get('step', 0))" 2>/dev/null || echo 0; }
resume_flag() { if ls "$1"/checkpoints/step_*.pt > /dev/null 2>&1; then echo --resume; fi; }
train() {  # RUN STEPS [overrides...]
  local run=$1 steps=$2
  shift 2
  [ "$(last_step "$run")" = "$steps" ] && return 0
  u4d train-diffusion "$PRESET" "steps=$steps" "${COMMON[@]}" "$@" --out "$run" --no-progress $(resume_flag "$run")
}
bank() {  # OUT [overrides...]: 16 scans, both stages 20 steps of DPM-Solver++(2M) SDE, the mean start
  local out=$1
  shift
  python3 -c "import json,sys; sys.exit(0 if json.load(open('$out/manifest.json')).get('complete') else 1)" \
    2>/dev/null && return 0
  u4d generate configs/u4d/generate_hdl64.yaml --out "$out" num=16 batch_size=4 stage1_steps=20 "$@" --no-progress
}
score() {  # NAME NET...: the denoising probe (NET: NAME=WEIGHTS[@stage]) and the gates of NAME's bank
  local name=$1
  shift
  [ -f "$P/$name/denoise.json" ] || python3 benchmarks/diagnostics/diag_denoise.py --root data/sim_eval --probs data/sim_eval_probs \
    --sequences 00 --num 4 --nets "$@" --out "$P/$name/denoise.json" > /dev/null
  if [ -f benchmarks/gates.py ] && [ ! -f "$P/$name/gates.json" ]; then
    python3 benchmarks/gates.py --bank "$name=$P/$name/bank" --real data/sim_eval --real-sequences 00-11 --num 16 \
      --out "$P/$name/gates.json" > /dev/null
  fi
}
shared() {  # NAME STEPS [overrides...]: one u4d net for both stages
  local name=$1 steps=$2
  shift 2
  train "$P/$name/net" "$steps" stage=u4d diffusion.cond_noise=0.05 "$@"
  bank "$P/$name/bank" mode=u4d "net=$P/$name/net" stage1= stage2=
  score "$name" "stage1=$P/$name/net@stage1" "stage2=$P/$name/net@stage2"
}
two_nets() {  # NAME STEPS [overrides...]: today's two nets, STEPS / 2 each
  local name=$1 half=$(($2 / 2))
  shift 2
  train "$P/$name/stage1" "$half" stage=stage1 "$@"
  train "$P/$name/stage2" "$half" stage=stage2 "$@"
  bank "$P/$name/bank" mode=u4d net= "stage1=$P/$name/stage1" "stage2=$P/$name/stage2"
  score "$name" "stage1=$P/$name/stage1" "stage2=$P/$name/stage2"
}
baseline() {  # NAME STEPS [overrides...]: the R2DM-style single net
  local name=$1 steps=$2
  shift 2
  train "$P/$name/net" "$steps" stage=baseline "$@"
  bank "$P/$name/bank" mode=baseline "baseline=$P/$name/net"
  score "$name" "baseline=$P/$name/net"
}

WIDE_STEPS=$((BUDGET * 10 / 19))  # base 24 + attention: 1.9x the base-16 step time (measured side by side)
ROUND=${ROUND:-1}
if [ "$ROUND" = 2 ]; then  # the loss weighting of the high-SNR end, where every round-1 pilot left the noise in x̂0
  if [ "$CORE" = A ]; then
    shared shared_simple "$BUDGET" diffusion.min_snr_gamma=null
  else
    shared shared_gamma50 "$BUDGET" diffusion.min_snr_gamma=50
  fi
elif [ "$CORE" = A ]; then
  two_nets two_nets "$BUDGET"
  shared shared_cosine_margin "$BUDGET" "${COSINE[@]}" crop_margin=32
  shared shared_cosine_margin_v "$BUDGET" "${COSINE[@]}" crop_margin=32 diffusion.parameterization=v
else
  shared shared "$BUDGET"
  shared shared_cosine "$BUDGET" "${COSINE[@]}"
  shared shared_wide_cosine_margin "$WIDE_STEPS" "${COSINE[@]}" crop_margin=32 "${WIDE[@]}"
fi
echo "pilots $CORE done"
