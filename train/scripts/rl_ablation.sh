#!/bin/bash
# The RL rows of the ablation (grpo, pada*, pada) from a kept SFT base, at the study's settings (docs/training.md
# "GPU runs"): every RL run on one GPU of the host, the runs spread over the GPUs, each run
# resuming from its last checkpoint when the script is run again.
#
#   physcene artifacts restore small-sft
#   BASE=artifacts/small-sft bash train/scripts/rl_ablation.sh                 # anchors, RL, evaluation
#   STOP_IN=540 STAGES="anchors rl" bash train/scripts/rl_ablation.sh          # under a 10-minute limit;
#   STOP_IN=540 STAGES=rl bash train/scripts/rl_ablation.sh                    # again until STEPS, then
#   STAGES=eval bash train/scripts/rl_ablation.sh                              # every kept checkpoint
#   physcene train ablation-merge --config small ablation.output=docs/results/ablation.json \
#     --sources runs/rl/s0/ablation.json runs/rl/s1/ablation.json --layouts docs/results/ablation
#
# Stages: anchors (the base's greedy layouts of POOL training prompts, TTO-repaired, and of HELDOUT prompts
# outside the pool: all GPUs), rl (the VARIANTS x SEEDS runs, PER_GPU at a time on each GPU: slot k taking
# runs k, k + GPUS * PER_GPU, ...), eval (per seed: reference, sft, sft+tto, each variant with every checkpoint
# on N_TEST test scenes, rule judge, and each model's NLL of the held-out anchors: $RUN/s<seed>/ablation.json).
# The reward is the paper's with the validity terms (floating, shrunk, out of zone: VALID='[]' for the
# bare reward), advantages scaled over the batch (SCALE=group: the paper's per-group scaling), G rollouts
# per prompt, global batch BATCH. Logs: $RUN/s<seed>/<variant>.log.
set -euo pipefail
BASE=${BASE:-artifacts/small-sft}
CONFIG=${CONFIG:-small}
RUN=${RUN:-runs/rl}
VARIANTS=${VARIANTS:-"pada grpo pada_star"}
SEEDS=${SEEDS:-"0 1"}
POOL=${POOL:-4096}                  # training prompts with an anchor (those whose reference fits TOKENS)
HELDOUT=${HELDOUT:-256}             # anchors of prompts outside the pool: each evaluated model's NLL of them
G=${G:-16}
BATCH=${BATCH:-128}                 # completions per optimiser step (BATCH / G prompts)
MICRO=${MICRO:-16}                  # of BATCH, per forward/backward
SCALE=${SCALE:-batch}
VALID=${VALID:-"[floating,shrunk,out_of_zone]"}
STEPS=${STEPS:-300}                 # optimiser steps per run: 300 x 128 = 38,400 rollouts (the paper: ~37 k)
SAVE=${SAVE:-50}                    # a checkpoint (kept, with optimiser state) every SAVE steps: the curves' points
TOKENS=${TOKENS:-2304}              # rollout and anchor length bound (the paper's)
N_TEST=${N_TEST:-866}
RL_CACHE=${RL_CACHE:-fast+fused+cudnn}  # sampled groups
EVAL_CACHE=${EVAL_CACHE:-fast}      # anchors and evaluation (greedy): HF's ids; fast+fused+cudnn: ~1.4x faster
STOP_IN=${STOP_IN:-}                # seconds: every run stops (and saves) this long after the script started
EXTRA=${EXTRA:-}
STAGES=${STAGES:-"anchors rl eval"}
GPUS=${GPUS:-$(python3 -c "import torch; print(max(1, torch.cuda.device_count()))")}
PER_GPU=${PER_GPU:-1}               # RL runs sharing one GPU at a time (a 27 M model leaves an H100 idle between
                                    # its kernels: 2 fill the gaps of one)
want() { [[ " $STAGES " == *" $1 "* ]]; }
stamp() { echo "[$(date +%T)] $*"; }
mkdir -p "$RUN"
deadline=${STOP_IN:+$(($(date +%s) + STOP_IN))}
left() { [ -n "$deadline" ] && echo "STOP_IN=$((deadline - $(date +%s)))"; }  # what is left of STOP_IN now
common="sft.output_dir=$BASE anchors.output=$RUN/anchors.jsonl.gz anchors.pool_size=$POOL $EXTRA"
held=$RUN/anchors_heldout.jsonl.gz  # (named here: a RUN= word of a later command would change $RUN inside it)
heldout="anchors.exclude=$RUN/anchors.jsonl.gz anchors.output=$held anchors.pool_size=$HELDOUT"
rl="pada.num_generations=$G pada.scale_rewards=$SCALE pada.reward=[\"valid_terms=$VALID\"]"
rl="$rl pada.max_steps=$STEPS pada.save_steps=$SAVE pada.save_total_limit=null"

if want anchors; then
  stamp "anchors: $POOL prompts on $GPUS GPU(s)"
  env $(left) NPROC=$GPUS RUN="$RUN" STAGES=anchors ANCHORS=$POOL MAX_TOKENS=$TOKENS CACHE=$EVAL_CACHE \
    EXTRA="$common" bash train/scripts/ablation_small.sh
  stamp "held-out anchors: $HELDOUT prompts outside the pool"
  env $(left) NPROC=$GPUS RUN="$RUN" STAGES=anchors ANCHORS=$HELDOUT MAX_TOKENS=$TOKENS CACHE=$EVAL_CACHE \
    EXTRA="$common $heldout" bash train/scripts/ablation_small.sh
fi
if want rl; then
  runs=()
  for seed in $SEEDS; do for variant in $VARIANTS; do runs+=("$seed:$variant"); done; done
  slots=$((GPUS * PER_GPU))
  for slot in $(seq 0 $((slots - 1))); do
    (
      gpu=$((slot % GPUS))
      for k in $(seq "$slot" "$slots" $((${#runs[@]} - 1))); do
        seed=${runs[$k]%%:*} variant=${runs[$k]##*:}
        dir=$RUN/s$seed  # (not RUN=...: a later word of the same command would read the new value)
        mkdir -p "$dir"
        stamp "$variant seed $seed on GPU $gpu"
        CUDA_VISIBLE_DEVICES=$gpu env $(left) NPROC=1 CONFIG=$CONFIG RUN="$dir" STAGES="$variant" PORT=$((29600 + 10 * k)) \
          ANCHORS=$POOL MAX_TOKENS=$TOKENS PADA_TOKENS=$TOKENS PADA_BATCH=$BATCH PADA_MICRO=$MICRO \
          PADA_MIN=100000 PADA_CACHE=$RL_CACHE CACHE=$EVAL_CACHE EXTRA="$common $rl seed=$seed" \
          bash train/scripts/ablation_small.sh > "$dir/$variant.log" 2>&1 \
          || stamp "$variant seed $seed failed: $dir/$variant.log"
      done
    ) &
  done
  wait
fi
if want eval; then
  seeds=($SEEDS)
  for k in "${!seeds[@]}"; do
    seed=${seeds[$k]}
    (
      gpu=$((k % GPUS)) dir=$RUN/s$seed
      stamp "eval seed $seed on GPU $gpu"
      listed=$(echo $VARIANTS | tr ' ' ,)
      CUDA_VISIBLE_DEVICES=$gpu NPROC=1 CONFIG=$CONFIG RUN="$dir" STAGES=eval ANCHORS=$POOL \
        MAX_TOKENS=$TOKENS N_TEST=$N_TEST PADA_MIN=100000 CACHE=$EVAL_CACHE PADA_TOKENS=$TOKENS \
        PADA_BATCH=$BATCH PADA_MICRO=$MICRO \
        EXTRA="$common $rl seed=$seed ablation.checkpoints=true ablation.reference=true ablation.variants=[$listed] \
ablation.output=$dir/ablation.json ablation.layouts=$dir/layouts \
ablation.heldout_anchors=$held" \
        bash train/scripts/ablation_small.sh > "$dir/eval.log" 2>&1 || stamp "eval seed $seed failed: $dir/eval.log"
    ) &
    if (((k + 1) % GPUS == 0)); then wait; fi
  done
  wait
fi
stamp done
