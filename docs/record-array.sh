#!/usr/bin/env bash
# The record of record on a cluster: one SLURM array task per training seed, each writing one
# share, then one pool. Submit from the repository root:
#
#   sbatch --array=58-71 docs/record-array.sh          # one share per seed; a class's seeds
#                                                      # start at 58 (0-57 are taken: record.run.FRESH_SEEDS_FROM)
#   sbatch --dependency=afterok:<job id> --wrap \
#     ".venv/bin/python -m e2e_lite.record pool outputs-*/shares/share-seeds-*.json"
#
# Each task trains every row of the record for its seed and drives its run of the sealed block;
# the pool refuses a share of another commit, settings or profile, a seed twice, and a share
# edited after it was written. The scheduler options are examples: set them for your cluster.
#SBATCH --job-name=e2e-lite-record
#SBATCH --cpus-per-task=16
#SBATCH --gres=gpu:1
#SBATCH --time=04:00:00
#SBATCH --output=record-%A_%a.log
set -euo pipefail
seed="${SLURM_ARRAY_TASK_ID:?submit with sbatch --array=FIRST-LAST}"
# a folder of outputs per task: tasks on shared storage never write the same files
export E2E_LITE_OUTPUTS="outputs-seed-${seed}"
.venv/bin/python -m e2e_lite.record run --seeds "${seed}-${seed}" --miles "${MILES:-150}"
