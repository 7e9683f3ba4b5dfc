#!/usr/bin/env bash
# Data-parallel train-vlm on Slurm: 4 ranks through srun (PMIx), chatsplat built with
# `cargo build --release --features mpi` against the cluster's OpenMPI.
#   sbatch deploy/slurm-train-vlm.sh
#SBATCH --job-name=chatsplat-train-vlm
#SBATCH --ntasks=4
#SBATCH --cpus-per-task=2
#SBATCH --mem-per-cpu=2G
#SBATCH --time=04:00:00
set -euo pipefail
srun --mpi=pmix chatsplat train-vlm --config checkpoints/tabletop-llava-ov/train_config.json --out out/tabletop-vlm
