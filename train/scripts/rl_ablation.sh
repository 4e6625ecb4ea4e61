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
#   RUNS="0:pada_star 1:pada 1:grpo" bash train/scripts/rl_ablation.sh         # these runs only
#   DRY=1 RUNS="0:pada_star 1:pada" GPUS=2 bash train/scripts/rl_ablation.sh   # print the commands, run none
#   FIRST_GPU=1 GPUS=1 RUN=runs/other bash train/scripts/rl_ablation.sh        # a second study on GPU 1 alone
#
# Runs: RUNS names them one by one as seed:variant words (variant: grpo, pada_star or pada); unset, they
# are every SEEDS x VARIANTS pair. A malformed word stops the script before anything runs (exit 2).
# Stages: anchors (the base's greedy layouts of POOL training prompts, TTO-repaired, and of HELDOUT prompts
# outside the pool: all the study's GPUs), rl (the runs, PER_GPU at a time on each GPU: slot k taking runs k,
# k + GPUS * PER_GPU, ...), eval (per seed with a run: reference, sft, sft+tto, each of the seed's variants
# with every checkpoint on N_TEST test scenes, rule judge, and each model's NLL of the held-out anchors:
# $RUN/s<seed>/ablation.json; give eval the RUNS the runs had), decode (the same rows' layouts only, into
# $RUN/s<seed>/layouts, PER_GPU seeds at a time on each GPU: ablation.decode_only; eval run elsewhere on
# them re-scores them without decoding; not in the default STAGES).
# DRY=1 prints each ablation_small.sh command (its environment, its log) instead of running it, the
# stages one after the other; nothing is written.
# The reward is the paper's with the validity terms (floating, shrunk, out of zone: VALID='[]' for the
# bare reward), advantages scaled over the batch (SCALE=group: the paper's per-group scaling), G rollouts
# per prompt, global batch BATCH. Logs: $RUN/s<seed>/<variant>.log.
set -euo pipefail
BASE=${BASE:-artifacts/small-sft}
CONFIG=${CONFIG:-small}
RUN=${RUN:-runs/rl}
VARIANTS=${VARIANTS:-"pada grpo pada_star"}
SEEDS=${SEEDS:-"0 1"}
RUNS=${RUNS:-}                      # seed:variant words (unset: every SEEDS x VARIANTS pair)
DRY=${DRY:-}                        # 1: print the commands instead of running them
POOL=${POOL:-4096}                  # training prompts with an anchor (those whose reference fits TOKENS)
HELDOUT=${HELDOUT:-256}             # anchors of prompts outside the pool: each evaluated model's NLL of them
G=${G:-16}
BATCH=${BATCH:-128}                 # completions per optimiser step (BATCH / G prompts)
MICRO=${MICRO:-16}                  # of BATCH, per forward/backward
SCALE=${SCALE:-batch}
VALID=${VALID:-"[floating,shrunk,out_of_zone]"}
STEPS=${STEPS:-300}                 # optimiser steps per run: 300 x 128 = 38,400 rollouts (the paper: ~37 k)
SAVE=${SAVE:-50}                    # a checkpoint (kept, with optimiser state) every SAVE steps: the curves' points
STOP_OVERRULED=${STOP_OVERRULED:-0.2}  # a run stops (saving) once the constraint overrules this share of its sampled
                                    # tokens over 5 steps: its policy has left the grammar (null: never)
CHECKPOINTS=${CHECKPOINTS:-true}    # the kept checkpoints decode / eval take as rows: true (all) or steps ([100,200])
TOKENS=${TOKENS:-2304}              # rollout and anchor length bound (the paper's)
N_TEST=${N_TEST:-866}
RL_CACHE=${RL_CACHE:-fast+fused+cudnn}  # sampled groups
EVAL_CACHE=${EVAL_CACHE:-fast}      # anchors and evaluation (greedy): HF's ids; fast+fused+cudnn: ~1.4x faster
PORTS=${PORTS:-29600}               # rendezvous ports: run k's from PORTS + 10 k, then each seed's table's (two
                                    # studies on one host: PORTS apart)
STOP_IN=${STOP_IN:-}                # seconds: every run stops (and saves) this long after the script started
EXTRA=${EXTRA:-}
STAGES=${STAGES:-"anchors rl eval"}
FIRST_GPU=${FIRST_GPU:-0}           # the study's GPUs: FIRST_GPU ... FIRST_GPU + GPUS - 1 (two studies on one host:
                                    # each on GPUs of its own)
GPUS=${GPUS:-$(python3 -c "import torch; print(max(1, torch.cuda.device_count() - $FIRST_GPU))")}
gpus=$(seq -s, "$FIRST_GPU" $((FIRST_GPU + GPUS - 1)))  # CUDA_VISIBLE_DEVICES of a stage on all of them
PER_GPU=${PER_GPU:-1}               # RL runs sharing one GPU at a time (a 27 M model leaves an H100 idle between
                                    # its kernels: 2 fill the gaps of one; a 61.6 M run holds ~20 GB of an 80 GB
                                    # H100: 2 fit, 4 ran out of memory)
want() { [[ " $STAGES " == *" $1 "* ]]; }
stamp() { echo "[$(date +%T)] $*"; }

# The runs as seed:variant words, checked before anything runs.
if [ -n "$RUNS" ]; then
  read -ra runs <<< "$RUNS" && named=RUNS
else
  runs=() && named="SEEDS x VARIANTS"
  for seed in $SEEDS; do for variant in $VARIANTS; do runs+=("$seed:$variant"); done; done
fi
for k in "${!runs[@]}"; do
  word=${runs[$k]} seed=${runs[$k]%%:*} variant=${runs[$k]#*:}
  if [[ "$word" != *:* || ! "$seed" =~ ^[0-9]+$ || " grpo pada_star pada " != *" $variant "* ]]; then
    echo "rl_ablation.sh: $named: '$word' is not seed:variant (seed an integer; variant grpo, pada_star or pada)" >&2
    exit 2
  fi
  if [[ " ${runs[*]:0:$k} " == *" $word "* ]]; then
    echo "rl_ablation.sh: $named: '$word' is named twice" >&2
    exit 2
  fi
done
seeds=()                            # the seeds with a run, in the order they first appear
for word in "${runs[@]}"; do [[ " ${seeds[*]} " == *" ${word%%:*} "* ]] || seeds+=("${word%%:*}"); done
variants_of() {  # $1: a seed: its runs' variants, comma-separated (ablation.variants)
  local word out=()
  for word in "${runs[@]}"; do [ "${word%%:*}" = "$1" ] && out+=("${word#*:}"); done
  (IFS=,; echo "${out[*]}")
}

quoted() {  # the words of a command as a shell reads them back (quotes only where needed)
  local word out=()
  for word in "$@"; do [[ "$word" =~ ^[][A-Za-z0-9_./:=,+@%-]*$ ]] && out+=("$word") || out+=("${word@Q}"); done
  echo "${out[*]}"
}
small() {  # $1: a log ('': this script's output), then NAME=value words: ablation_small.sh in that environment
  local log=$1; shift
  local cmd=(env "$@" bash train/scripts/ablation_small.sh)
  if [ "$DRY" = 1 ]; then
    echo "$(quoted "${cmd[@]}")${log:+ > $log 2>&1}"
  elif [ -n "$log" ]; then
    mkdir -p "$(dirname "$log")" && "${cmd[@]}" > "$log" 2>&1
  else
    "${cmd[@]}"
  fi
}
spawn() { if [ "$DRY" = 1 ]; then "$@"; else "$@" & fi; }  # in the background (DRY=1: in turn)

[ "$DRY" = 1 ] || mkdir -p "$RUN"
deadline=${STOP_IN:+$(($(date +%s) + STOP_IN))}
left() { [ -z "$deadline" ] || echo $((deadline - $(date +%s))); }  # what is left of STOP_IN now (none: '')
common="sft.output_dir=$BASE anchors.output=$RUN/anchors.jsonl.gz anchors.pool_size=$POOL $EXTRA"
held=$RUN/anchors_heldout.jsonl.gz  # (named here: a RUN= word of a later command would change $RUN inside it)
heldout="anchors.exclude=$RUN/anchors.jsonl.gz anchors.output=$held anchors.pool_size=$HELDOUT"
rl="pada.num_generations=$G pada.scale_rewards=$SCALE pada.reward=[\"valid_terms=$VALID\"]"
rl="$rl pada.max_steps=$STEPS pada.save_steps=$SAVE pada.save_total_limit=null pada.stop_overruled=$STOP_OVERRULED"

rl_slot() {  # $1: a slot (GPU FIRST_GPU + $1 % GPUS): runs $1, $1 + GPUS * PER_GPU, ... one after the other
  local gpu=$((FIRST_GPU + $1 % GPUS)) k seed variant dir
  for k in $(seq "$1" $((GPUS * PER_GPU)) $((${#runs[@]} - 1))); do
    seed=${runs[$k]%%:*} variant=${runs[$k]#*:} dir=$RUN/s${runs[$k]%%:*}
    stamp "$variant seed $seed on GPU $gpu"
    small "$dir/$variant.log" CUDA_VISIBLE_DEVICES="$gpu" STOP_IN="$(left)" NPROC=1 CONFIG="$CONFIG" RUN="$dir" \
      STAGES="$variant" PORT=$((PORTS + 10 * k)) ANCHORS="$POOL" MAX_TOKENS="$TOKENS" PADA_TOKENS="$TOKENS" \
      PADA_BATCH="$BATCH" PADA_MICRO="$MICRO" PADA_MIN=100000 PADA_CACHE="$RL_CACHE" CACHE="$EVAL_CACHE" \
      EXTRA="$common $rl seed=$seed" || stamp "$variant seed $seed failed: $dir/$variant.log"
  done
}
eval_seed() {  # $1: a seed, $2: its GPU, $3: eval or decode, $4: the seed's index (its ports): the seed's
  # table (decode: its layouts only, ablation.decode_only), its variants those it has runs of
  local dir=$RUN/s$1 only=${3:-eval}
  stamp "$only seed $1 on GPU $2: $(variants_of "$1")"
  small "$dir/$only.log" CUDA_VISIBLE_DEVICES="$2" NPROC=1 CONFIG="$CONFIG" RUN="$dir" STAGES=eval \
    PORT=$((PORTS + 10 * (${#runs[@]} + $4))) \
    ANCHORS="$POOL" MAX_TOKENS="$TOKENS" N_TEST="$N_TEST" PADA_MIN=100000 CACHE="$EVAL_CACHE" \
    PADA_TOKENS="$TOKENS" PADA_BATCH="$BATCH" PADA_MICRO="$MICRO" \
    EXTRA="$common $rl seed=$1 ablation.checkpoints=$CHECKPOINTS ablation.reference=true \
ablation.variants=[$(variants_of "$1")] ablation.output=$dir/ablation.json ablation.layouts=$dir/layouts \
ablation.heldout_anchors=$held$([ "$only" = decode ] && echo " ablation.decode_only=true")" \
    || stamp "$only seed $1 failed: $dir/$only.log"
}

if want anchors; then
  stamp "anchors: $POOL prompts on $GPUS GPU(s)"
  small "" CUDA_VISIBLE_DEVICES="$gpus" STOP_IN="$(left)" NPROC="$GPUS" RUN="$RUN" STAGES=anchors \
    ANCHORS="$POOL" MAX_TOKENS="$TOKENS" CACHE="$EVAL_CACHE" EXTRA="$common"
  stamp "held-out anchors: $HELDOUT prompts outside the pool"
  small "" CUDA_VISIBLE_DEVICES="$gpus" STOP_IN="$(left)" NPROC="$GPUS" RUN="$RUN" STAGES=anchors \
    ANCHORS="$HELDOUT" MAX_TOKENS="$TOKENS" CACHE="$EVAL_CACHE" EXTRA="$common $heldout"
fi
if want rl; then
  for slot in $(seq 0 $((GPUS * PER_GPU - 1))); do spawn rl_slot "$slot"; done
  wait
fi
if want decode; then  # PER_GPU seeds at a time on each GPU
  for k in "${!seeds[@]}"; do
    spawn eval_seed "${seeds[$k]}" $((FIRST_GPU + k % GPUS)) decode "$k"
    if (((k + 1) % (GPUS * PER_GPU) == 0)); then wait; fi
  done
  wait
fi
if want eval; then
  for k in "${!seeds[@]}"; do
    spawn eval_seed "${seeds[$k]}" $((FIRST_GPU + k % GPUS)) eval "$k"
    if (((k + 1) % GPUS == 0)); then wait; fi
  done
  wait
fi
stamp "done"
