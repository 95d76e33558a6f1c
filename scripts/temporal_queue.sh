#!/bin/bash
# The long runs of the temporal table (the paper's Table 2, the MoST fusion ablation, the gate figure) as one list of
# idempotent tasks that two queues, one per CPU core, share: each queue takes the first task whose inputs are ready and
# that no live queue holds (a claim file in RUNS/temporal/claims with its boot id and pid), so the two stages of one
# U4D method train side by side and a method lands within hours. After an interruption run the same commands again:
# claims of queues that ended are taken over and every task resumes from its checkpoints. From the repository root:
#   CORE=A nohup bash scripts/temporal_queue.sh > temporal_A.log 2>&1 &
#   CORE=B nohup bash scripts/temporal_queue.sh > temporal_B.log 2>&1 &
# Every sequence net is the single-frame net of its stage (SOURCE_STAGES, default weights/) fine-tuned on L = 4 frame windows by
# configs/u4d/cpu_hdl64_most.yaml (MoST blocks and the ego-motion input start as the identity), STEPS per U4D stage
# and 2 x STEPS for the baseline, so each method gets the same budget:
#   u4d_most         U4D stage 1 + stage 2 with MoST (gating fusion), seeds 0 and 1
#   baseline_most    the R2DM-style net with MoST, seeds 0 and 1
#   u4d_no_temporal  U4D stage 1 + stage 2 fine-tuned alike without MoST (net.most=false), seeds 0 and 1
#   fusion_<v>       U4D with net.most_fusion=cascade|add|concat, seed 0 (gating is u4d_most seed 0)
# Each generates 24 sequences of 5 frames (TTCE k = 4 needs 5 frames; the temporal convolution and the poses relative
# to frame 0 carry over from L = 4) along ego motions drawn from the training places, scored by `u4d evaluate`
# against the held-out places 88-99; the floor scores those real held-out sequences themselves. The queue that finds
# everything done writes the table (benchmarks/reports/temporal_table.py ->
# benchmarks/results/temporal/temporal.json / .md); u4d_most seed 0 draws the gate figures.
# RUNS (default ../runs) says where run folders go, RESULTS (default benchmarks/results/temporal) where the table and
# figure go (PY, default python3, runs benchmarks/reports/temporal_table.py). Each finished method-seed leaves its
# evaluation and its training budget in EVALS (default RESULTS/temporal_evals, committed): a method with one there is
# not run again, so the table grows over sessions on different machines although run folders and checkpoints stay on
# the machine.
# PROPAGATE=1 generates every sequence with propagate=true (frame 0 moved along the ego motion into the later frames,
# the rest completed: u4d_aug.propagate) into banks NAME_prop_sSEED, scores them into RESULTS/temporal_evals_propagated
# and writes RESULTS/temporal_propagated.json / .md; it reuses every trained net on the machine and trains the missing
# ones. The floor (real sequences) is the same in both and is scored once, into RESULTS/temporal_evals/floor.
# ONE_NET=1 trains U4D as one net for both stages (train-diffusion stage=u4d, the recipe of the final single-frame
# nets): u4d_most, baseline_most and u4d_no_temporal, seeds 0 and 1 (no fusion variants), fine-tuned from SOURCE_U4D
# (default weights/u4d.pt, a one-net u4d exported by `u4d export-weights`) and SOURCE_BASELINE (default
# weights/baseline.pt), each with its source's diffusion settings (`u4d_aug.stage.diffusion_overrides`: the loss it
# was trained on, e.g. cond_noise=0.05 min_snr_gamma=null). Budget as above: every batch of the one net trains both
# tasks, a window each, so it runs STEPS steps of 2 windows, the baseline's 2 x STEPS windows. Its runs, banks and
# claims go to RUNS/temporal_one_net, its evaluations to RESULTS/temporal_evals_one_net[_propagated], its table to
# RESULTS/temporal_one_net[_propagated].json / .md (u4d gates: most_gates_one_net[_stage1].png); with PROPAGATE=1 as
# above. The two modes share the world and the floor and can run side by side.
# The world is DATA/sim_seg (DATA default data, then a link to RUNS/data unless the checkout has one) and its
# probabilities DATA/sim_seg_probs (the same commands as scripts/downstream_queue.sh), the first task.
set -euo pipefail
RUNS=${RUNS:-../runs}
DATA=${DATA:-data}
RESULTS=${RESULTS:-benchmarks/results/temporal}
PY=${PY:-python3}
STEPS=${STEPS:-2000}
CORE=${CORE:?set CORE=A or CORE=B}
export OMP_NUM_THREADS=1
WAIT=${WAIT:-120}  # seconds between looks for a task whose inputs the other queue is writing
ONE_NET=${ONE_NET:-0}
SOURCE_U4D=${SOURCE_U4D:-weights/u4d.pt}
SOURCE_BASELINE=${SOURCE_BASELINE:-weights/baseline.pt}
SOURCE_STAGES=${SOURCE_STAGES:-weights}  # the two-net mode's folder of u4d_stage1.pt / u4d_stage2.pt
if [ "$ONE_NET" != 1 ] && { [ ! -f "$SOURCE_STAGES/u4d_stage1.pt" ] || [ ! -f "$SOURCE_STAGES/u4d_stage2.pt" ]; }; then
  echo "temporal_queue.sh: the two-net mode fine-tunes $SOURCE_STAGES/u4d_stage1.pt and u4d_stage2.pt, which are not" \
    "there (the shipped U4D is one net, weights/u4d.pt): run with ONE_NET=1, or set SOURCE_STAGES to a folder" \
    "holding two stage nets (git show 3fe7096:weights/u4d_stage1.pt > DIR/u4d_stage1.pt, likewise stage 2)" >&2
  exit 2
fi
if [ "$ONE_NET" = 1 ]; then MODE=_one_net; else MODE=; fi
T=$RUNS/temporal$MODE
PROPAGATE=${PROPAGATE:-0}
if [ "$PROPAGATE" = 1 ]; then
  E=${EVALS:-$RESULTS/temporal_evals${MODE}_propagated} BANK=_prop_s TABLE=temporal${MODE}_propagated
  PROP=(propagate=true)
else
  E=${EVALS:-$RESULTS/temporal_evals$MODE} BANK=_s TABLE=temporal$MODE PROP=()
fi
FLOOR=$RESULTS/temporal_evals/floor
PRESET=configs/u4d/cpu_hdl64_most.yaml
FRD=weights/extractor_frd.pt

resume_flag() { if ls "$1"/checkpoints/step_*.pt > /dev/null 2>&1; then echo --resume; fi; }
last_step() { tail -n 1 "$1/log.jsonl" 2>/dev/null | python3 -c "import sys,json; print(json.loads(sys.stdin.read() or '{}').get('step', 0))" 2>/dev/null || echo 0; }
done_bank() { python3 -c "import json,sys; sys.exit(0 if json.load(open('$1/manifest.json')).get('complete') else 1)" 2>/dev/null; }
keep() {  # NAME: ./NAME links to RUNS/NAME unless it is there, so the world and banks outlive a new checkout
  mkdir -p "$RUNS/$1"
  [ -e "$1" ] || ln -sn "$(cd "$RUNS/$1" && pwd)" "$1" 2> /dev/null || [ -e "$1" ]  # the other core may link first
}

finetune() {  # RUN STAGE STEPS [overrides...]: one sequence net from the shipped net of its stage
  local run=$1 stage=$2 steps=$3
  shift 3
  [ "$(last_step "$run")" = "$steps" ] && return 0
  u4d train-diffusion "$PRESET" "stage=$stage" "steps=$steps" "init_from=$SOURCE_STAGES/u4d_$stage.pt" \
    "data_root=$DATA/sim_seg" "probs_root=$DATA/sim_seg_probs" sample_every=0 "$@" --out "$run" --no-progress \
    $(resume_flag "$run")
}
recipe() {  # NET: the diffusion.* overrides of the loss NET was trained on, for a fine-tune that starts from it
  "$PY" - "$1" <<'PYEOF'
import sys
from u4d_aug.pipeline import load_generator
from u4d_aug.stage import diffusion_overrides
print(" ".join(diffusion_overrides(load_generator(sys.argv[1]).config.diffusion)))
PYEOF
}
finetune_one() {  # RUN SEED [overrides...]: one U4D sequence net for both stages from SOURCE_U4D, 2 windows a step
  local run=$1 seed=$2 loss
  shift 2
  [ "$(last_step "$run")" = "$STEPS" ] && return 0
  loss=$(recipe "$SOURCE_U4D")
  # shellcheck disable=SC2086  # $loss: one override per word
  u4d train-diffusion "$PRESET" stage=u4d "steps=$STEPS" batch_size=2 "init_from=$SOURCE_U4D" $loss \
    "data_root=$DATA/sim_seg" "probs_root=$DATA/sim_seg_probs" sample_every=0 "seed=$seed" "$@" --out "$run" \
    --no-progress $(resume_flag "$run")
}
finetune_baseline() {  # RUN SEED
  local run=$1 seed=$2 loss=
  [ "$(last_step "$run")" = "$((2 * STEPS))" ] && return 0
  if [ "$ONE_NET" = 1 ]; then loss=$(recipe "$SOURCE_BASELINE"); fi
  # shellcheck disable=SC2086  # $loss: one override per word
  u4d train-diffusion "$PRESET" stage=baseline "steps=$((2 * STEPS))" "init_from=$SOURCE_BASELINE" $loss \
    "data_root=$DATA/sim_seg" sample_every=0 "seed=$seed" --out "$run" --no-progress $(resume_flag "$run")
}
sequences() {  # OUT MODE SEED [overrides...]: 24 sequences of 5 frames along motions of the nets' training places
  local out=$1 mode=$2 seed=$3
  shift 3
  done_bank "$out" || u4d generate configs/u4d/generate_hdl64.yaml --out "$out" "mode=$mode" num=24 frames=5 \
    "seed=$((1000 * seed))" "${PROP[@]}" "$@" --no-progress
}
world() {  # the simulated world and the uncertainty segmentor's probabilities of its training places
  if [ ! -f "$DATA/sim_seg/done" ]; then
    # 164 places: 00-87 train, 88-99 held out, 100-163 the ceiling arm's real bank (configs/experiment/design_*.yaml)
    u4d simulate --out "$DATA/sim_seg" --sequences 164 --frames 8 --seed 10 --config configs/sim/seg_rich.yaml
    touch "$DATA/sim_seg/done"
  fi
  if [ ! -f "$DATA/sim_seg_probs/done" ]; then
    u4d seg-predict weights/uncertainty_segmentor.pt "$DATA/sim_seg" --out "$DATA/sim_seg_probs" --sequences 00-87 \
      --no-progress
    touch "$DATA/sim_seg_probs/done"
  fi
}
score() {  # BANK OUT: TTCE k = 3, 4 (ICP from the identity and from a global registration), CTC k = 1..4 and FRD
  [ -f "$2/evaluation.json" ] || u4d evaluate --bank "$1" --real "$DATA/sim_seg" --real-sequences 88-99 \
    --metrics ttce,ttce_global,ctc,frd --extractor-frd "$FRD" --json --md --out "$2" --no-progress
}
budget() {  # OUT RUN...: each net's steps, training minutes (its log), stage and batch (its config) and the host
  "$PY" - "$@" <<'PYEOF'
import json, os, sys
import yaml
from u4d_aug.host import host_info
out, runs = sys.argv[1], sys.argv[2:]
nets = {}
for run in runs:
    last = [json.loads(line) for line in open(os.path.join(run, "log.jsonl")) if '"time"' in line][-1]
    net = {"steps": last["step"], "minutes": round(last["time"] / 60, 1)}
    if os.path.isfile(os.path.join(run, "config.yaml")):
        config = yaml.safe_load(open(os.path.join(run, "config.yaml")))
        net |= {"stage": config["diffusion"]["stage"], "batch_size": config["batch_size"]}
    nets[os.path.basename(run.rstrip("/"))] = net
with open(os.path.join(out, "budget.json.tmp"), "w") as f:
    json.dump({"nets": nets, "host": host_info()}, f, indent=2)
os.replace(os.path.join(out, "budget.json.tmp"), os.path.join(out, "budget.json"))
PYEOF
}
method() {  # NAME SEED: generate and score one trained U4D-like method (u4d_most, u4d_no_temporal, fusion_*)
  local name=$1 seed=$2 run=$T/${1}_s$2
  if [ "$ONE_NET" = 1 ]; then
    sequences "$T/banks/$name$BANK$seed" u4d "$seed" "net=$run/u4d" stage1= stage2=
  else
    sequences "$T/banks/$name$BANK$seed" u4d "$seed" net= "stage1=$run/stage1" "stage2=$run/stage2"
  fi
  score "$T/banks/$name$BANK$seed" "$E/${name}_s$seed"
  if [ "$name" = u4d_most ] && [ "$seed" = 0 ] && [ "$PROPAGATE" = 0 ]; then  # the gate figures of the trained model (+ json beside)
    if [ "$ONE_NET" = 1 ]; then
      u4d gates "$run/u4d" --role stage2 --png "$RESULTS/most_gates_one_net.png"
      u4d gates "$run/u4d" --role stage1 --png "$RESULTS/most_gates_one_net_stage1.png"
    else
      u4d gates "$run/stage2" --png "$RESULTS/most_gates.png"
      u4d gates "$run/stage1" --png "$RESULTS/most_gates_stage1.png"
    fi
  fi
  if [ "$ONE_NET" = 1 ]; then budget "$E/${name}_s$seed" "$run/u4d"; else budget "$E/${name}_s$seed" "$run/stage1" "$run/stage2"; fi
}
baseline_method() {  # SEED: generate and score one trained baseline
  local seed=$1
  sequences "$T/banks/baseline_most$BANK$seed" baseline "$seed" "baseline=$T/baseline_most_s$seed"
  score "$T/banks/baseline_most$BANK$seed" "$E/baseline_most_s$seed"
  budget "$E/baseline_most_s$seed" "$T/baseline_most_s$seed"
}
floor() {  # the held-out real sequences 88-99 as the bank: their own TTCE / CTC
  mkdir -p "$T/floor/sequences"
  for s in $(seq 88 99); do ln -sfn "$(realpath "$DATA/sim_seg/sequences/$s")" "$T/floor/sequences/$s"; done
  [ -f "$FLOOR/evaluation.json" ] || u4d evaluate --bank "$T/floor" --real "$DATA/sim_seg" \
    --real-sequences 88-99 --metrics ttce,ttce_global,ctc --json --md --out "$FLOOR" --no-progress
}

# The tasks, in the order the queues take them: "KIND ARGS..." with done_KIND (its result exists), ready_KIND (its
# inputs exist) and run_KIND.
TASKS=("world")
LAST=()
if [ "$ONE_NET" = 1 ]; then  # nets of one length: U4D and the baseline of a seed side by side
  for entry in u4d_most:0: baseline:0 u4d_most:1: baseline:1 u4d_no_temporal:0:net.most=false \
    u4d_no_temporal:1:net.most=false; do
    IFS=: read -r name seed over <<< "$entry"
    if [ "$name" = baseline ]; then
      TASKS+=("baseline $seed" "finish_baseline $seed")
    else
      TASKS+=("net $name $seed${over:+ $over}" "finish $name $seed")
    fi
  done
else
  for entry in u4d_most:0: u4d_no_temporal:0:net.most=false u4d_most:1: u4d_no_temporal:1:net.most=false baseline:0 \
    baseline:1 fusion_cascade:0:net.most_fusion=cascade fusion_add:0:net.most_fusion=add \
    fusion_concat:0:net.most_fusion=concat; do
    IFS=: read -r name seed over <<< "$entry"
    if [ "$name" = baseline ]; then
      TASKS+=("finish_baseline $seed")
      LAST+=("baseline $seed")
    else
      TASKS+=("stage $name $seed stage1${over:+ $over}" "stage $name $seed stage2${over:+ $over}" "finish $name $seed")
    fi
  done
fi
TASKS+=("floor" "${LAST[@]}")  # two nets: the baselines' trainings, the longest tasks, once nothing else is ready

done_world() { [ -f "$DATA/sim_seg_probs/done" ]; }
ready_world() { true; }
run_world() { world; }
done_stage() { [ -f "$E/${1}_s$2/budget.json" ] || [ "$(last_step "$T/${1}_s$2/$3")" = "$STEPS" ]; }
ready_stage() { done_world; }
run_stage() {
  local name=$1 seed=$2 stage=$3
  shift 3
  finetune "$T/${name}_s$seed/$stage" "$stage" "$STEPS" "seed=$seed" "$@"
}
done_net() { [ -f "$E/${1}_s$2/budget.json" ] || [ "$(last_step "$T/${1}_s$2/u4d")" = "$STEPS" ]; }
ready_net() { done_world; }
run_net() {
  local name=$1 seed=$2
  shift 2
  finetune_one "$T/${name}_s$seed/u4d" "$seed" "$@"
}
done_finish() { [ -f "$E/${1}_s$2/budget.json" ]; }
ready_finish() {
  if [ "$ONE_NET" = 1 ]; then done_net "$1" "$2"; else done_stage "$1" "$2" stage1 && done_stage "$1" "$2" stage2; fi
}
run_finish() { method "$1" "$2"; }
done_baseline() { [ -f "$E/baseline_most_s$1/budget.json" ] || [ "$(last_step "$T/baseline_most_s$1")" = "$((2 * STEPS))" ]; }
ready_baseline() { [ -f "$DATA/sim_seg/done" ]; }
run_baseline() { finetune_baseline "$T/baseline_most_s$1" "$1"; }
done_finish_baseline() { [ -f "$E/baseline_most_s$1/budget.json" ]; }
ready_finish_baseline() { done_baseline "$1"; }
run_finish_baseline() { baseline_method "$1"; }
done_floor() { [ -f "$FLOOR/evaluation.json" ]; }
ready_floor() { [ -f "$DATA/sim_seg/done" ]; }
run_floor() { floor; }

BOOT=$(cat /proc/sys/kernel/random/boot_id 2> /dev/null || hostname)
CLAIMS=$T/claims
claim() {  # TASK-ID: take the task unless a live queue holds it (a queue of an earlier boot or a dead pid does not)
  mkdir -p "$CLAIMS"
  (
    flock 9
    held="$CLAIMS/$1"
    if [ -f "$held" ]; then
      read -r boot pid < "$held" || true
      if [ "$boot" = "$BOOT" ] && [ "$pid" != "$$" ] && kill -0 "$pid" 2> /dev/null; then exit 1; fi
    fi
    echo "$BOOT $$" > "$held"
  ) 9> "$CLAIMS/.lock"
}
release() { rm -f "$CLAIMS/$1"; }

if [ "$DATA" = data ]; then keep data; fi
while true; do  # take the first ready task nobody holds; wait while the other queue holds what is left
  left=0
  ran=0
  for task in "${TASKS[@]}"; do
    read -r -a words <<< "$task"
    kind=${words[0]}
    args=("${words[@]:1}")
    "done_$kind" "${args[@]}" && continue
    left=1
    "ready_$kind" "${args[@]}" || continue
    id=$(echo "$task" | tr ' =' '__')
    claim "$id" || continue
    echo "queue $CORE: $task ($(date -u +%Y-%m-%dT%H:%M))"
    "run_$kind" "${args[@]}"
    release "$id"
    ran=1
    break
  done
  [ "$ran" = 1 ] && continue
  [ "$left" = 0 ] && break
  sleep "$WAIT"
done
if claim table; then  # every method-seed and the floor are scored: the table (a queue finishing later rewrites it)
  FUSION=()  # the MoST fusion ablation: two nets only
  if [ "$ONE_NET" != 1 ]; then
    FUSION=(--fusion "gating=$E/u4d_most_s0" --fusion "cascade=$E/fusion_cascade_s0"
      --fusion "add=$E/fusion_add_s0" --fusion "concat=$E/fusion_concat_s0")
  fi
  "$PY" benchmarks/reports/temporal_table.py \
    --method "u4d_most=$E/u4d_most_s0" --method "u4d_most=$E/u4d_most_s1" \
    --method "baseline_most=$E/baseline_most_s0" --method "baseline_most=$E/baseline_most_s1" \
    --method "u4d_no_temporal=$E/u4d_no_temporal_s0" --method "u4d_no_temporal=$E/u4d_no_temporal_s1" \
    --method "floor=$FLOOR" "${FUSION[@]}" --out "$RESULTS/$TABLE"
  release table
fi
echo "temporal queue $CORE done"
