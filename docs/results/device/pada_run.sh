#!/bin/bash
# One PADA run on a lent one-GPU machine, in /tmp/run (a copy of the working tree), started detached:
#   (PADA_MIN=20 STAGES='pada eval' setsid nohup bash docs/results/device/pada_run.sh > /tmp/pada_run.log 2>&1 &)
# SEED: tar chunks (concatenated) holding runs/small/sft + the anchors (session 14's `.wp/s2.*`).
# RESUME: a runs/small/pada tar.xz to resume from (a snapshot.sh or end-of-run ckpt.tar.xz), if present.
# Knobs of the run: PADA_MIN, STAGES ('pada' or 'pada eval'), LAMBDA, TERMS, SIZE, DENOISE, SCOPE, CHARGE.
# Ends by packing the results to /tmp/outA and touching /tmp/run/A_DONE; poll with poll.sh.
set -uo pipefail
export PYTHONPATH=/tmp/wp PYTHONUNBUFFERED=1
src=$(pwd)
SEED=${SEED:-/tmp/s2.0 /tmp/s2.1 .wp/s2.2 .wp/s2.3 .wp/s2.4}
RESUME=${RESUME:-.wp/ckpt.tar.xz}
rm -rf /tmp/run && mkdir -p /tmp/run /tmp/outA
tar -C "$src" --exclude=./.wp --exclude=./data -cf - . | tar -C /tmp/run -xf -
(cd "$src" && cat $SEED) | tar -C /tmp/run -xf -
(cd "$src" && [ -f "$RESUME" ] && xz -dc "$RESUME") | tar -C /tmp/run -xf - 2>/dev/null && [ -d /tmp/run/runs/small/pada ] \
  && echo "resuming from $RESUME"
cd /tmp/run
python3 -m pip install -q --no-deps --no-build-isolation -e . >/dev/null 2>&1 || echo "editable install failed"
stamp() { echo "[$(date +%T)] $*"; }
stamp start; nvidia-smi --query-gpu=name --format=csv,noheader; ls runs/small runs/small/pada 2>/dev/null
physcene assets bake --device cuda:0 2>&1 | tail -1
stamp bake-done
NPROC=1 CONSTRAINED=1 PADA_MIN=${PADA_MIN:-20} PADA_LEVEL=3 PADA_TOKENS=2304 PADA_BATCH=64 PADA_MICRO=8 \
  ANCHORS=512 N_TEST=200 DECIMALS=2 PADA_CACHE=static_compile \
  EXTRA="anchors.output=runs/small/anchors_l3.jsonl.gz pada.epochs=40 pada.generation_batches=4 pada.num_iterations=2 pada.save_steps=8 pada.save_total_limit=1 ablation.variants=[pada] pada.object_credit=${LAMBDA:-0.5} pada.object_credit_terms=${TERMS:-[penetration,floating,out_of_zone,size]} pada.reward=[size_per_cm=${SIZE:-0.5}] pada.denoise=${DENOISE:-1.0} pada.object_credit_scope=${SCOPE:-numbers} pada.object_credit_penetration=${CHARGE:-pairs}" \
  STAGES="${STAGES:-pada}" bash docs/results/ablation_small.sh
stamp pada-done
cp runs/small/pada/train_log.json /tmp/outA/pada_train_log.json 2>/dev/null
cp runs/small/pada/physcene_run.json /tmp/outA/pada_run.json 2>/dev/null
if [ -d runs/small/ablation ]; then
  cp docs/results/ablation.json /tmp/outA/ablation_run.json; cp docs/results/ablation.md /tmp/outA/ablation_run.md
  tar -cJf /tmp/outA/layouts.tar.xz runs/small/ablation
fi
tar -cf - runs/small/pada | xz -1 | split -b 15M - /tmp/outA/ckpt.tar.xz.   # parts < 16 MiB come back
ls -la /tmp/outA
touch /tmp/run/A_DONE
