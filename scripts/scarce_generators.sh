#!/bin/bash
# The generators of the downstream experiment's data-scarce setting (configs/experiment/design_scarce.yaml): the one
# U4D net and the R2DM-style baseline trained on the setting's 18 places only (its 9 labelled places and its
# unlabelled pool of 9), no other scans and no fine-tune of the main nets, at a smaller stated budget (STEPS, default
# 8,000 steps each, the final nets' recipe and batch), then a bank of NUM scans from each for the arms mt+u4d and
# mt+r2dm. U4D's uncertainty comes from SEGMENTOR, a segmentor trained on those places' labels only (default: the
# setting's sup-only run of seed 1; the places are read from its run folder: splits/*.json names the labelled ones,
# config.yaml the unlabelled pool). One core, resumable, from the repository root:
#   nohup bash scripts/scarce_generators.sh > ../runs/scarce_generators.log 2>&1 &
# Writes DATA/scarce_probs (the segmentor's probabilities on the 18 places), RUNS/scarce/{u4d,baseline}[_milestones]
# (scripts/generator_final.sh: segments, milestones scored by the gates) and BANKS/scarce_{u4d,r2dm}_hdl64.
# The cascade recipe (u4d_aug.cascade): LAYOUT, the layout nets' overrides, and DETAIL, the detail level of the
# milestones and the banks (nearest, or a detail net trained on these places only):
#   LAYOUT="height=64 width=256 crop_width=0 net.attention=true net.attention_heads=4" DETAIL=nearest bash ...
set -euo pipefail
RUNS=${RUNS:-../runs}
STEPS=${STEPS:-8000}
SEGMENT=${SEGMENT:-4000}
NUM=${NUM:-512}
LAYOUT=${LAYOUT:-}
DETAIL=${DETAIL:-}
SEGMENTOR=${SEGMENTOR:-$RUNS/design_scarce/runs/sup-only/minkunet/seed1/model.pt}
DATA=${DATA:-data}  # the world (DATA/sim_seg) and where the probabilities go
BANKS=${BANKS:-banks}  # where configs/experiment/design_scarce.yaml reads the banks
PROBS=$DATA/scarce_probs
export OMP_NUM_THREADS=1
[ -f "$SEGMENTOR" ] || { echo "SEGMENTOR: $SEGMENTOR not found (train it: OMP_NUM_THREADS=1 u4d experiment \
configs/experiment/design_scarce.yaml 'seeds=[1]' --arms sup-only)" >&2; exit 2; }
read -r -a places <<< "$(python3 - "$(dirname "$SEGMENTOR")" <<'PY'
import glob, json, sys
import yaml
folder = sys.argv[1]
splits = glob.glob(f"{folder}/splits/*.json")
if len(splits) != 1:
    sys.exit(f"{folder}/splits: expected one split file, found {len(splits)}")
labelled = {seq for seq, _ in json.load(open(splits[0]))["labeled"]}
try:
    with open(f"{folder}/config.yaml") as f:
        pool = (yaml.safe_load(f) or {}).get("data", {}).get("unlabeled_sequences")
except OSError as exc:
    sys.exit(f"{folder}/config.yaml: cannot read the segmentor's run config ({exc.strerror})")
if not pool:
    sys.exit(f"{folder}/config.yaml: data.unlabeled_sequences is empty: not a run of the data-scarce setting")
print(" ".join(sorted(labelled | {str(p) for p in pool})))
PY
)"
echo "scarce places (${#places[@]}): ${places[*]}"
if [ ! -f "$PROBS/done" ]; then
  u4d seg-predict "$SEGMENTOR" "$DATA/sim_seg" --sequences "${places[@]}" --out "$PROBS" --no-progress
  touch "$PROBS/done"
fi
quoted=$(printf '"%s",' "${places[@]}")
NAME=scarce METHOD=both STEPS=$STEPS SEGMENT=$SEGMENT RUNS=$RUNS DETAIL=$DETAIL \
  EXTRA="sequences=[${quoted%,}] probs_root=$PROBS $LAYOUT" bash scripts/generator_final.sh
cascade=()
[ -z "$DETAIL" ] || cascade=("detail=$DETAIL")
done_bank() { python3 -c "import json,sys; sys.exit(0 if json.load(open('$1/manifest.json')).get('complete') else 1)" 2>/dev/null; }
F=$RUNS/scarce
done_bank "$BANKS/scarce_u4d_hdl64" || u4d generate configs/u4d/generate_hdl64.yaml --out "$BANKS/scarce_u4d_hdl64" \
  mode=u4d "net=$F/u4d_milestones/step_$STEPS.pt" stage1= stage2= "num=$NUM" ${cascade[@]+"${cascade[@]}"} --no-progress
done_bank "$BANKS/scarce_r2dm_hdl64" || u4d generate configs/u4d/generate_hdl64.yaml --out "$BANKS/scarce_r2dm_hdl64" \
  mode=baseline "baseline=$F/baseline_milestones/step_$STEPS.pt" "num=$NUM" ${cascade[@]+"${cascade[@]}"} --no-progress
echo "scarce generators done"
