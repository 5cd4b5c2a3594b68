#!/usr/bin/env bash
# Re-measures every evaluation in docs/ with a model (default: the shipped weights), as the README quotes them:
# ModelNet40 unseen (100 pairs per setting, and the peers' protocol), the seen split and the embedded set (50
# per setting), the Stanford Dragon scans, the 3DMatch scenes (40 pairs per list) and kitchen fragments, the LiDAR pair and the angle sweep. Baselines are taken from each directory's earlier
# results.json where they were scored on the same pairs with the same options (evaluate.py --reuse), so after a
# change of weights or thresholds only DIT, DIT+ICP and the pipeline run again.
#
#   bash scripts/remeasure_docs.sh [CHECKPOINT] [DATA_DIR] [SCANS_DIR] [SHARED_DATA_DIR]
#   STEPS="embedded peers" bash scripts/remeasure_docs.sh    # only the named steps
#
# Each step writes its log beside its output in runs/remeasure/ (ignored by git); the first failure stops it.
set -euo pipefail
cd "$(dirname "$0")/.."
checkpoint=${1:-dit_jax/weights/dit-cpu-modelnet40}
data=${2:-../shared/data/modelnet40_ply_hdf5_1024}
scans=${3:-../shared/data/stanford_dragon_stand}
shared=${4:-../shared/data}
logs=runs/remeasure
mkdir -p "$logs"
all=(icp fpfh_ransac fgr fpfh_ransac_icp fgr_icp)

step() {  # step NAME ARGS...: one evaluate.py run, timed, logged to runs/remeasure/NAME.log
  local name=$1
  shift
  if [[ -n ${STEPS:-} && " $STEPS " != *" $name "* ]]; then return 0; fi
  echo "$(date -u +%H:%M:%S) $name" >&2
  local start=$SECONDS
  python evaluate.py --checkpoint "$checkpoint" --no-progress "$@" > "$logs/$name.log" 2>&1 \
    || { tail -5 "$logs/$name.log" >&2; exit 1; }
  echo "$name: $((SECONDS - start)) s" >&2
}

step unseen --data-dir "$data" --unseen --settings all --max-pairs 100 --baselines "${all[@]}" \
  --reuse docs/eval_modelnet40_unseen --out docs/eval_modelnet40_unseen
step dragon --scans "$scans" --baselines "${all[@]}" --out docs/eval_stanford_dragon
step rooms --scans "$shared/3dmatch" --max-pairs 40 --baselines open3d_room_5cm open3d_room_full features \
  --out docs/eval_3dmatch
step kitchen --scans "$shared/3dmatch_redkitchen" --baselines fpfh_ransac_icp --out docs/eval_3dmatch_redkitchen
step lidar --scans "$shared/lidar_pair" --baselines fpfh_ransac_icp --out docs/eval_lidar_pair
step seen --data-dir "$data" --settings all --max-pairs 50 --baselines "${all[@]}" \
  --reuse docs/eval_modelnet40_seen --out docs/eval_modelnet40_seen
step embedded --settings all --max-pairs 50 --baselines "${all[@]}" --reuse docs/eval_embedded --out docs/eval_embedded
step peers --data-dir "$data" --unseen --variant peers --settings clean low_noise_partial high_noise_partial \
  --max-pairs 100 --baselines "${all[@]}" --reuse docs/eval_modelnet40_unseen_peers \
  --out docs/eval_modelnet40_unseen_peers
step angle_sweep --data-dir "$data" --unseen --angle-sweep --max-pairs 16 --out docs/eval_modelnet40_unseen
