#!/bin/bash
# Latent-generator runs (issue "Scans with walls": LiDM-style latent diffusion on a range-image autoencoder): the one
# U4D net and the baseline on configs/u4d/latent_hdl64.yaml, trained on the latents of the autoencoder AE in
# segments of SEGMENT steps up to STEPS; after each segment the EMA weights are exported
# (RUNS/latent/NAME/METHOD_milestones/step_N.pt), 16 scans generated (both stages 20 steps of DPM-Solver++(2M) SDE,
# the mean start of the training latents) and scored by benchmarks/gates.py with the real scans through AE beside
# them (the best a generator on AE can do). Resumable; one core each:
#   AE=../runs/latent/ae16/autoencoder.pt NAME=ae16 METHOD=u4d nohup bash scripts/latent_pilot.sh > LOG 2>&1 &
# or both methods on one core, segment by segment, so that their budgets are equal whenever the queue stops:
#   AE=... NAME=ae16 METHOD=both nohup bash scripts/latent_pilot.sh > LOG 2>&1 &
# EXTRA: more train-diffusion overrides (net size, lr), e.g. EXTRA="net.base_channels=48".
set -euo pipefail
RUNS=${RUNS:-../runs}
AE=${AE:?set AE to the autoencoder weights, OUT/autoencoder.pt of u4d train-autoencoder}
NAME=${NAME:?set NAME, the pilot folder under RUNS/latent}
METHOD=${METHOD:?set METHOD=u4d, baseline or both}
STEPS=${STEPS:-4000}
SEGMENT=${SEGMENT:-2000}
read -r -a extra <<< "${EXTRA:-}"
F=$RUNS/latent/$NAME
if [ "$METHOD" = both ]; then
  for ((target = SEGMENT; target <= STEPS; target += SEGMENT)); do
    for m in u4d baseline; do METHOD=$m STEPS=$target bash "$0"; done
  done
  exit 0
fi
export OMP_NUM_THREADS=1

last_step() {  # the last logged step of run folder $1 (0 before its first log line)
  [ -f "$1/log.jsonl" ] || { echo 0; return; }
  tail -n 1 "$1/log.jsonl" | python3 -c "import sys,json; print(json.loads(sys.stdin.read() or '{}').get('step', 0))"
}
resume_flag() { if ls "$1"/checkpoints/step_*.pt > /dev/null 2>&1; then echo --resume; fi; }
if [ "$METHOD" = u4d ]; then stage=(stage=u4d diffusion.cond_noise=0.1); else stage=(stage=baseline); fi
run=$F/$METHOD
milestones=$F/${METHOD}_milestones
mkdir -p "$milestones"
for ((target = SEGMENT; target <= STEPS; target += SEGMENT)); do
  weights=$milestones/step_$target.pt
  if [ "$(last_step "$run")" -lt "$target" ]; then
    u4d train-diffusion configs/u4d/latent_hdl64.yaml "steps=$target" "${stage[@]}" "autoencoder=$AE" \
      ${extra[@]+"${extra[@]}"} --out "$run" --no-progress $(resume_flag "$run")
  fi
  [ -f "$weights" ] || { [ "$(last_step "$run")" = "$target" ] && u4d export-weights "$run" --out "$weights"; }
  bank=$milestones/bank_$target
  if ! python3 -c "import json,sys; sys.exit(0 if json.load(open('$bank/manifest.json')).get('complete') else 1)" 2>/dev/null; then
    if [ "$METHOD" = u4d ]; then
      u4d generate configs/u4d/generate_hdl64.yaml --out "$bank" mode=u4d "net=$weights" stage1= stage2= num=16 \
        batch_size=4 stage1_steps=20 --no-progress
    else
      u4d generate configs/u4d/generate_hdl64.yaml --out "$bank" mode=baseline "baseline=$weights" num=16 \
        batch_size=4 --no-progress
    fi
  fi
  [ -f "$milestones/gates_$target.json" ] || "${PY:-python3}" benchmarks/gates.py --bank "${METHOD}_$target=$bank" \
    --autoencoder "ae=$AE" --real data/sim_eval --real-sequences 00-11 --num 16 --work "$F/gates_work" \
    --out "$milestones/gates_$target.json" > /dev/null
done
echo "latent $NAME $METHOD done"
