#!/bin/bash
# The `small` ablation (docs/results/ablation.json) on the GPUs of one host, every stage under
# accelerate (DDP, one process per GPU), in about 20 minutes of 2 x H200:
#
#   bash train/scripts/ablation_small.sh                       # all GPUs, runs/small, defaults below
#   NPROC=1 SFT_MIN=30 PADA_MIN=10 bash train/scripts/ablation_small.sh   # longer, one GPU
#   STAGES="synth sft" bash train/scripts/ablation_small.sh                # part of it (then the rest:
#   STAGES="anchors grpo pada_star pada eval" EXTRA="anchors.cache=static" bash ...)
#   NPROC=1 PARALLEL=1 PADA_MIN=14 STAGES="grpo pada_star pada" bash ...  # the 3 RL variants at once
#   STAGES=plan bash train/scripts/ablation_small.sh        # the SFT model's layouts with the order and
#                                                          # parents free and from its plan (first GPU)
#   physcene artifacts restore small-sft && STAGES="anchors grpo pada_star pada eval" \
#     EXTRA="sft.output_dir=artifacts/small-sft" bash ...  # RL from the kept SFT base, no SFT stage
#
# Stages resume: rerunning continues SFT from its last checkpoint, keeps a complete anchor file
# and reuses finished models (`ablation.reuse`). Step times land in each stage's train_log.json.
set -euo pipefail
NPROC=${NPROC:-$(python3 -c "import torch; print(max(1, torch.cuda.device_count()))")}
CONFIG=${CONFIG:-small}
RUN=${RUN:-runs/$CONFIG}
DATA=${DATA:-data/train.jsonl}      # `synth` builds it; any CTRC JSONL works
SFT_MIN=${SFT_MIN:-7}
PADA_MIN=${PADA_MIN:-2.5}
ANCHORS=${ANCHORS:-256}
N_TEST=${N_TEST:-200}
MAX_TOKENS=${MAX_TOKENS:-4096}      # test-split completions are 914-2,791 tokens
PADA_BATCH=${PADA_BATCH:-64}        # completions per GPU per step (G = 4 -> 16 prompts)
PARALLEL=${PARALLEL:-}              # 1: the RL variants train at the same time on the same GPU(s), each
                                    # logging to $RUN/<variant>.log (one H100: 1.37x the steps per hour of
                                    # one variant at a time; docs/training.md)
PADA_MICRO=${PADA_MICRO:-$([ "$PARALLEL" = 1 ] && echo 8 || echo "$PADA_BATCH")}
                                    # of PADA_BATCH, per forward/backward (accumulation PADA_BATCH /
                                    # PADA_MICRO; TRL still generates PADA_BATCH per GPU at once); lower it
                                    # for long completions: ~1 GB of activations per 4,000-token row in
                                    # bf16 (PARALLEL=1: 8; three processes at 64 ran an H100 out of memory)
PADA_TOKENS=${PADA_TOKENS:-$MAX_TOKENS}  # max_completion_length of PADA generation
WORKERS=${WORKERS:-$(nproc)}
LAUNCH=${LAUNCH:-"accelerate launch --config_file configs/accelerate/multi_gpu.yaml --num_processes $NPROC"}
PADA_LEVEL=${PADA_LEVEL:-null}      # PADA prompts of level <= this only (null: all levels)
SFT_STEPS=${SFT_STEPS:--1}          # optimizer steps of SFT (-1: the config's epochs)
CONSTRAINED=${CONSTRAINED:-}        # 1 / 0: anchors, PADA groups and eval decode under the CTRC constraint
                                    # or not (unset: the config's choice; `small`: constrained)
CACHE=${CACHE:-static_compile}      # KV cache of anchor and eval generation (H200: 3.4x dynamic)
PADA_CACHE=${PADA_CACHE:-}          # KV cache of PADA's group generation (unset: the config's); a
                                    # variant that fails with a static cache is run again with dynamic
EXTRA=${EXTRA:-}                    # more key=value overrides for every stage
SYNTH_EXTRA=${SYNTH_EXTRA:-}        # configs/data.yaml overrides for synth, e.g. noise.enabled=false (the
                                    # synthesiser's clean layouts: docs/results.md "The base model")
SFT_EXTRA=${SFT_EXTRA:-}            # overrides for the SFT stage only (e.g. model.init_from=DIR to go on
                                    # from an earlier SFT checkpoint, sft.per_device_batch_size=32)
N_TRAIN=${N_TRAIN-40000}            # synthetic training scenes (the train split: 9,429; the artifact small-sft: 40,000)
DECIMALS=${DECIMALS-2}              # digits after the point in the synthesised completions and the anchors
                                    # ("": physcene.ctrc.DECIMALS = 5; 1 pushes resting contacts into each other)
PLAN_BATCH=${PLAN_BATCH:-128}       # plan: scenes decoded at once (512 fits the small and medium configs on an H100)
PLAN_ROWS=${PLAN_ROWS:-"sft sft+plan"}  # plan: the rows decoded (sft+plan: the ablation's decoding)
STOP_IN=${STOP_IN:-}                # seconds: SFT and PADA stop (and save) this long after the script started, so
                                    # a job's time limit (a scheduler's, a remote command's) does not kill them mid-step;
                                    # unlike SFT_MIN / PADA_MIN it counts synthesis, tokenising and loading
STAGES=${STAGES:-"synth sft anchors grpo pada_star pada eval"}  # also: plan (not by default)

stamp() { echo "[$(date +%T)] $*"; }
common="output_dir=$RUN data.train=$DATA eval.max_new_tokens=$MAX_TOKENS anchors.max_new_tokens=$MAX_TOKENS"
common="$common anchors.n_records=$ANCHORS"  # every stage: the eval stage checks the anchor file is complete
common="$common pada.max_completion_length=$PADA_TOKENS pada.per_device_batch_size=$PADA_MICRO"
common="$common pada.global_batch_size=$((PADA_BATCH * NPROC)) pada.max_level=$PADA_LEVEL"
common="$common anchors.cache=$CACHE eval.cache=$CACHE"
if [ "$CONSTRAINED" = 1 ]; then
  common="$common anchors.constrained=true eval.constrained=true pada.constrained=true"
elif [ "$CONSTRAINED" = 0 ]; then
  common="$common anchors.constrained=false eval.constrained=false pada.constrained=false"
fi
if [ -n "$DECIMALS" ]; then
  common="$common anchors.decimals=$DECIMALS pada.denoise_decimals=$DECIMALS"
fi
common="$common ablation.n_test=$N_TEST $EXTRA"
if [ -n "$STOP_IN" ]; then
  deadline=$(( $(date +%s) + STOP_IN ))
  common="$common sft.stop_at=$deadline pada.stop_at=$deadline"
fi
want() { [[ " $STAGES " == *" $1 "* ]]; }

have_warp() { python3 -c "import warp" > /dev/null 2>&1; }
if [ "$NPROC" -ge 1 ] && have_warp && python3 -c "import torch, sys; sys.exit(not torch.cuda.is_available())"; then
  # bake every asset's SDF on the GPU first: the cache key does not depend on the device, and a Warp
  # without its CPU compiler (as on some GPU hosts) cannot bake on the CPU (docs/training.md, "GPU runs");
  # a host without Warp runs sft, and synth and plan (decoding only) from a carried bake cache
  # (PHYSCENE_CACHE; docs/training.md, "GPU runs")
  physcene assets bake --device cuda:0 > /dev/null
fi
if want synth && [ ! -s "$DATA" ] && [[ "$DATA" != synth:* ]]; then
  stamp "synth -> $DATA"
  physcene data synth --split train --out "$(dirname "$DATA")" --workers "$WORKERS" ${N_TRAIN:+--n $N_TRAIN} \
    ${DECIMALS:+record.decimals=$DECIMALS} $SYNTH_EXTRA
fi
if want sft; then
  stamp "sft ($NPROC processes, $SFT_MIN min)"
  $LAUNCH -m physcene.cli train sft --config "$CONFIG" $common sft.max_minutes="$SFT_MIN" sft.max_steps="$SFT_STEPS" \
    sft.dataset_num_proc="$WORKERS" $SFT_EXTRA  # one process tokenizes 40,000 records in ~5 minutes
fi
if want anchors; then
  stamp "anchors ($ANCHORS records)"
  $LAUNCH -m physcene.cli train anchors --config "$CONFIG" $common
fi
pada_cache=${PADA_CACHE:+pada.cache=$PADA_CACHE}
train_variant() {  # $1: the variant, $2: a rendezvous port of its own (variants may run at once)
  local launch="$LAUNCH"
  [[ "$LAUNCH" == *"accelerate launch"* ]] && launch="$LAUNCH --main_process_port $2"
  stamp "$1 ($PADA_MIN min${PADA_CACHE:+, cache $PADA_CACHE})"
  $launch -m physcene.cli train pada --config "$CONFIG" --variant "$1" $common $pada_cache \
    pada.max_minutes="$PADA_MIN" && return 0
  if [ -n "$PADA_CACHE" ] && [ "$PADA_CACHE" != dynamic ]; then
    stamp "$1 failed with cache $PADA_CACHE; again with the dynamic cache"
    # (merged adapters exist for the fast decoder only: an EXTRA that merges them is overruled here)
    $launch -m physcene.cli train pada --config "$CONFIG" --variant "$1" $common pada.cache=dynamic \
      pada.merge_adapters=false pada.max_minutes="$PADA_MIN" && return 0
  fi
  stamp "$1 failed (the ablation retries it within its budget or reports it skipped)"
}
port=${PORT:-29510}                 # rendezvous ports PORT+1.. (runs sharing a host: ports of their own)
for variant in grpo pada_star pada; do
  want "$variant" || continue
  port=$((port + 1))
  if [ "$PARALLEL" = 1 ]; then
    mkdir -p "$RUN"
    stamp "$variant started in the background, log $RUN/$variant.log"
    train_variant "$variant" "$port" > "$RUN/$variant.log" 2>&1 &
  else
    train_variant "$variant" "$port"
  fi
done
wait  # the variants started in the background (PARALLEL=1)
if want eval; then
  stamp "eval ($N_TEST test scenes)"
  launch="$LAUNCH"  # a port of its own: the tables of several seeds may be made at once on one host
  [[ "$LAUNCH" == *"accelerate launch"* ]] && launch="$LAUNCH --main_process_port $((port + 1))"
  $launch -m physcene.cli train ablation --config "$CONFIG" $common \
    ablation.budget_min="$(python3 -c "print(10 * $PADA_MIN)")"
fi
if want plan; then
  decode_only=$(have_warp || echo --decode-only)  # no Warp: the completions only, to $RUN/plan_following/,
                                                  # scored elsewhere with --completions (docs/training.md)
  stamp "plan following ($N_TEST test scenes, the SFT model, first GPU${decode_only:+, decoding only})"
  python3 -m physcene.train.analysis.plan_following "$RUN/sft" --n "$N_TEST" --device cuda --cache fast \
    --max-new-tokens "$MAX_TOKENS" --batch-size "$PLAN_BATCH" --rows $PLAN_ROWS $decode_only \
    --out "$RUN/plan_following.json"
fi
stamp done
