#!/usr/bin/env bash
# Many scenes on Slurm: an array of 4 tasks, each runs its shard of the manifest (`chatsplat
# batch` reads SLURM_ARRAY_TASK_ID, SLURM_ARRAY_TASK_MIN and SLURM_ARRAY_TASK_COUNT). Requeued or
# re-submitted tasks skip finished scenes and resume interrupted ones.
#   sbatch deploy/slurm-batch-array.sh scenes.toml
#SBATCH --job-name=chatsplat-batch
#SBATCH --array=0-3
#SBATCH --cpus-per-task=2
#SBATCH --mem=8G
#SBATCH --time=04:00:00
#SBATCH --requeue
set -euo pipefail
manifest="${1:-scenes.toml}"
chatsplat batch --manifest "$manifest"
# once every task is done, any task (or a dependent job) merges the report again:
#   chatsplat batch --manifest scenes.toml --report
