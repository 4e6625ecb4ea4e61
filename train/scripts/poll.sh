#!/bin/bash
# poll.sh SECONDS DONE LOG: wait until DONE exists or SECONDS pass; print LOG's last TAILC bytes and the
# GPU state; then copy what there is to $OUT: the finished run's /tmp/outA, else a snapshot of the
# running job (snapshot.sh), so a machine taken back between polls loses only the steps since; and once,
# when the run has packed its SFT model + anchors (/tmp/run/S_DONE), those seed chunks (/tmp/outS).
here=$(cd "$(dirname "$0")" && pwd)
end=$((SECONDS + ${1:-500})); done_file=${2:-/tmp/run/A_DONE}; log=${3:-/tmp/pada_run.log}
while [ $SECONDS -lt $end ] && [ ! -e "$done_file" ]; do sleep 10; done
tail -c "${TAILC:-300}" "$log"; echo
nvidia-smi --query-gpu=utilization.gpu,memory.used --format=csv,noheader
[ -n "${OUT:-}" ] || exit 0
if [ -e "$done_file" ]; then cp /tmp/outA/* "$OUT"/; else bash "$here/snapshot.sh" /tmp/run/runs/small/pada "$OUT"; fi
if [ -e /tmp/run/S_DONE ] && [ ! -e /tmp/run/S_SENT ]; then cp /tmp/outS/* "$OUT"/ && touch /tmp/run/S_SENT; fi
