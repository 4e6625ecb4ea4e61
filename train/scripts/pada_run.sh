#!/bin/bash
# One `small` run on the GPUs of a remote host, in /tmp/run (a copy of the working tree), started detached.
# PADA from an SFT model + anchors carried in SEED chunks (one GPU):
#   (PADA_MIN=20 STAGES='pada eval' setsid nohup bash train/scripts/pada_run.sh > /tmp/pada_run.log 2>&1 &)
# The whole pipeline on all GPUs of the host, from training data synthesised elsewhere (DATA_XZ, a tar.xz of
# data/train.jsonl: a Warp build without its CPU compiler cannot synthesise on the host):
#   (DATA_XZ=.wp/data.tar.xz NPROC=2 STAGES='sft anchors pada eval' setsid nohup bash ... > /tmp/pada_run.log 2>&1 &)
# SEED: tar chunks (concatenated) holding runs/small/sft + the anchors, if present (`.wp/seed.a?`, written by
# this script's sft + anchors stages; docs/training.md, "Runs on a remote GPU host").
# RESUME: a runs/small/pada tar.xz to resume from (a snapshot.sh or end-of-run ckpt.tar.xz), if present.
# Knobs: NPROC, PADA_MIN, SFT_MIN, SFT_STEPS, STAGES (of sft anchors pada eval), LAMBDA, TERMS, SIZE,
# VALID (reward.valid_terms, '[]' for none), DENOISE, SCOPE, CHARGE.
# After the anchors stage the SFT model + anchors are packed to /tmp/outS as seed chunks (the next run's
# SEED) and /tmp/run/S_DONE is touched; at the end the results go to /tmp/outA (results.tar.xz:
# logs + table; layouts.tar.xz; ckpt.tar.xz.*) and /tmp/run/A_DONE is touched; poll with poll.sh.
set -uo pipefail
export PYTHONPATH=/tmp/wp PYTHONUNBUFFERED=1
src=$(pwd)
SEED=${SEED:-/tmp/seed.aa /tmp/seed.ab .wp/seed.ac .wp/seed.ad}
RESUME=${RESUME:-.wp/ckpt.tar.xz}
DATA_XZ=${DATA_XZ:-}
STAGES=${STAGES:-pada}
want() { [[ " $STAGES " == *" $1 "* ]]; }
rm -rf /tmp/run /tmp/outS /tmp/res && mkdir -p /tmp/run /tmp/outA /tmp/res
tar -C "$src" --exclude=./.wp --exclude=./data -cf - . | tar -C /tmp/run -xf -
seed=$(cd "$src" && for f in $SEED; do [ -f "$f" ] && echo "$f"; done)
[ -n "$seed" ] && (cd "$src" && cat $seed) | tar -C /tmp/run -xf -
[ -n "$DATA_XZ" ] && (cd "$src" && xz -dc "$DATA_XZ") | tar -C /tmp/run -xf -
(cd "$src" && [ -f "$RESUME" ] && xz -dc "$RESUME") | tar -C /tmp/run -xf - 2>/dev/null && [ -d /tmp/run/runs/small/pada ] \
  && echo "resuming from $RESUME"
cd /tmp/run
python3 -m pip install -q --no-deps --no-build-isolation -e . >/dev/null 2>&1 || echo "editable install failed"
stamp() { echo "[$(date +%T)] $*"; }
stamp start; nvidia-smi --query-gpu=name --format=csv,noheader; ls runs/small runs/small/pada data 2>/dev/null
physcene assets bake --device cuda:0 2>&1 | tail -1
stamp bake-done
NPROC=${NPROC:-1}
# the SFT recipe of docs/results/ablation_denoise.json (1,400 steps of global batch 64, lr 1e-3 cosine, 2-decimal text) and anchors
# (512 constrained generations of level <= 3, TTO-repaired); every stage's shared overrides in EXTRA
export NPROC CONSTRAINED=1 PADA_MIN=${PADA_MIN:-20} PADA_LEVEL=3 PADA_TOKENS=2304 PADA_BATCH=64 PADA_MICRO=8 \
  ANCHORS=512 N_TEST=200 DECIMALS=2 PADA_CACHE=static_compile SFT_MIN=${SFT_MIN:-12.5} \
  SFT_STEPS=${SFT_STEPS:-1400} SFT_EXTRA="sft.per_device_batch_size=32 sft.save_steps=400 sft.dataset_num_proc=16" \
  EXTRA="anchors.output=runs/small/anchors_l3.jsonl.gz pada.epochs=40 pada.generation_batches=4 pada.num_iterations=2 pada.save_steps=8 pada.save_total_limit=1 ablation.variants=[pada] pada.object_credit=${LAMBDA:-0.5} pada.object_credit_terms=${TERMS:-[penetration,floating,out_of_zone,size]} pada.reward=[size_per_cm=${SIZE:-0.5},\"valid_terms=${VALID:-[floating,shrunk]}\"] pada.denoise=${DENOISE:-1.0} pada.object_credit_scope=${SCOPE:-numbers} pada.object_credit_penetration=${CHARGE:-pairs}"
first=$(for s in sft anchors; do want $s && echo -n "$s "; done)
if [ -n "$first" ]; then
  STAGES="$first" bash train/scripts/ablation_small.sh
  stamp "$first-done"
  cp runs/small/sft/train_log.json /tmp/res/sft_train_log.json 2>/dev/null
  cp runs/small/anchors_l3*summary.json /tmp/res/anchors_summary.json 2>/dev/null
  mkdir -p /tmp/outS && tar --exclude='checkpoint-*' -cf - runs/small/sft runs/small/anchors_l3.* \
    | split -b 15M - /tmp/outS/seed.   # the next run's SEED (model weights: xz gains little)
  touch /tmp/run/S_DONE
fi
rest=$(for s in pada eval; do want $s && echo -n "$s "; done)
[ -n "$rest" ] && STAGES="$rest" bash train/scripts/ablation_small.sh
stamp pada-done
cp runs/small/pada/train_log.json /tmp/res/pada_train_log.json 2>/dev/null
cp runs/small/pada/physcene_run.json /tmp/res/pada_run.json 2>/dev/null
if [ -d runs/small/ablation ]; then
  cp docs/results/ablation.json /tmp/res/ablation_run.json; cp docs/results/ablation.md /tmp/res/ablation_run.md
  tar -cJf /tmp/outA/layouts.tar.xz runs/small/ablation
fi
[ -d runs/small/pada ] && tar -cf - runs/small/pada | xz -1 | split -b 15M - /tmp/outA/ckpt.tar.xz.   # parts < 16 MiB come back
tar -C /tmp/res -cJf /tmp/outA/results.tar.xz .   # the logs and the table, one file of the 8 that come back
ls -la /tmp/outA
touch /tmp/run/A_DONE
