#!/bin/bash
# rl_remote.sh start|again|poll|pack|send: the RL study (rl_ablation.sh) on a GPU host that runs commands
# under a time limit and loses its files when it is given back. The study runs detached in /tmp/run (a copy
# of the working tree, so a new copy of the tree cannot change a script while bash reads it; `start`
# installs that copy in editable mode, so the host's `physcene` is the copy's); each poll
# packs what a later host needs and sends it to $OUT; the next host's `start` unpacks it and goes on.
#
#   bash train/scripts/rl_remote.sh start        # copy the tree, unpack the carried state, start rl_ablation.sh
#   bash train/scripts/rl_remote.sh poll 540     # wait up to 540 s or until the study ends, print the runs'
#                                                # steps, pack the state, send its first parts to $OUT
#                                                # (exit 3 at once on a host where nothing was started:
#                                                # a host left idle is given back with the run)
#   bash train/scripts/rl_remote.sh send 4       # the pack's parts from the 5th on (a command brings back
#                                                # ~64 MB: SEND=4 parts of 15 MiB at a time)
#   STAGES=eval bash train/scripts/rl_remote.sh again  # rl_ablation.sh once more on what is there (refused
#                                                # while it still runs)
#   mkdir -p /tmp/state && cp .wp/state/* /tmp/state/   # the next host: the parts, carried in calls of their own
#   SCRIPT=train/scripts/ablation_small.sh RUN=runs/medium CONFIG=medium NPROC=2 STAGES="synth sft" \
#     bash train/scripts/rl_remote.sh start      # another script detached the same way (an SFT base: poll
#                                                # until it ends; pack then carries $RUN's files outside
#                                                # checkpoint-* folders: the final model, its logs)
#
# `start` passes the environment on to SCRIPT (default rl_ablation.sh: BASE, STAGES, VARIANTS, SEEDS, RUNS,
# STEPS, PER_GPU, STOP_IN, ...; RUN, default runs/rl, is the folder pack carries); it unpacks the parts
# STATE names (default /tmp/state/rl_state.tar.xz.*) into /tmp/run, and takes BASE from the tree (carry
# artifacts/small-sft). The state: the anchors, every run's newest complete checkpoint whole (the Trainer
# resumes from it), its earlier complete checkpoints without optimizer, scheduler and RNG state (the
# evaluation's curve points; a checkpoint being written is left out), the final adapters, logs, and the
# evaluation's tables and layouts, as rl_state.tar.xz.* parts under 16 MiB, kept in /tmp/run/pack until
# the next pack (PACK: elsewhere). The kept artifacts restored into runs/rl (docs/training.md, "GPU runs")
# and packed here (WORK=. PACK=/tmp/pack SEND=99 bash train/scripts/rl_remote.sh pack .wp/state) are the
# same state.
set -uo pipefail
here=$(cd "$(dirname "$0")" && pwd)
src=$(cd "$here/../.." && pwd)
work=${WORK:-/tmp/run}
RUN=${RUN:-runs/rl}                 # what pack carries (the run folder of SCRIPT)
SCRIPT=${SCRIPT:-train/scripts/rl_ablation.sh}  # what start runs detached
log=$work/rl.log
stamp() { echo "[$(date +%T)] $*"; }

pack() {  # the state as parts in $work/pack (kept on the host until the next pack)
  local dest=${PACK:-$work/pack} list parts
  [ -d "$work/$RUN" ] || { echo "pack: nothing under $work/$RUN yet"; return 0; }
  mkdir -p "$dest"
  list=$(mktemp)
  (
    cd "$work" || exit
    find "$RUN" -type f ! -path '*/checkpoint-*' ! -name '*.lock'
    for run in "$RUN"/s*/*/; do
      ckpts=$(checkpoints "$run") || exit
      newest=${ckpts##*$'\n'}  # the Trainer resumes from it
      for ckpt in $ckpts; do
        if [ "$ckpt" = "$newest" ]; then
          find "$ckpt" -type f
        else
          find "$ckpt" -type f ! -name 'optimizer.pt' ! -name 'scheduler.pt' ! -name 'rng_state*.pth'
        fi
      done
    done
  ) | sort -u > "$list" || { echo "pack: listing the checkpoints under $work/$RUN failed" >&2; rm -f "$list"; return 1; }
  rm -f "$dest"/rl_state.tar.xz.*
  tar -C "$work" -cf - -T "$list" | xz -1 -T0 | split -b 15M - "$dest/rl_state.tar.xz."
  parts=("$dest"/rl_state.tar.xz.*)
  echo "pack: $(wc -l < "$list") files -> ${#parts[@]} part(s), $(du -ch "${parts[@]}" | tail -1 | cut -f1)"
  rm -f "$list"
}

checkpoints() {  # $1: a run folder: its complete checkpoint-N folders, oldest first (one being written: left out)
  python3 -c 'import sys; from physcene.train.checkpoints import complete_checkpoints as c
sys.stdout.writelines(f"{p}\n" for p in c(sys.argv[1]))' "$1"
}

send() {  # $1: the first part (0-based), $2: where to: SEND parts (a command brings back ~64 MB in all)
  local parts
  parts=$(ls "${PACK:-$work/pack}"/rl_state.tar.xz.* 2>/dev/null | tail -n +$(($1 + 1)) | head -n "${SEND:-4}")
  [ -n "$parts" ] || { echo "send: no part from $1 on"; return 0; }
  mkdir -p "$2" && cp $parts "$2"/
  local total left
  total=$(ls "${PACK:-$work/pack}"/rl_state.tar.xz.* | wc -l)
  left=$((total - $1 - $(echo $parts | wc -w)))
  echo "send: $(echo $parts | wc -w) of $total part(s)$([ $left -gt 0 ] && echo "; the rest: send $((total - left))")"
}

progress() {  # every run's optimizer steps (its newest trainer_state or its log's last step line)
  for run in "$work/$RUN"/s*/*/; do
    [ -f "$run/physcene_run.json" ] || ls -d "$run"checkpoint-* > /dev/null 2>&1 || continue
    python3 - "$run" <<'EOF'
import json, sys
from pathlib import Path
run = Path(sys.argv[1])
states = sorted(run.glob("checkpoint-*/trainer_state.json"), key=lambda p: int(p.parent.name.split("-")[1]))
info = run / "physcene_run.json"
last = json.loads(states[-1].read_text()) if states else {}
steps = json.loads(info.read_text()).get("steps") if info.is_file() else last.get("global_step")
logs = [h for h in last.get("log_history", []) if "reward" in h]
tail = logs[-1] if logs else {}
print(f"{run.parent.name}/{run.name}: step {steps}, checkpoints {[p.parent.name.split('-')[1] for p in states]}, "
      f"reward {tail.get('reward')}, step_time {tail.get('step_time')}")
EOF
  done
}

running() {  # whether the script launch started in $work still runs
  [ -f "$work/PID" ] && kill -0 "$(cat "$work/PID")" 2> /dev/null
}

launch() {  # $SCRIPT detached in $work, with this environment; DONE holds its exit status
  if running; then
    echo "rl_remote: $SCRIPT is still running (pid $(cat "$work/PID")): poll until it ends" >&2
    return 1
  fi
  rm -f "$work/DONE"
  RUN=$RUN SCRIPT=$SCRIPT setsid nohup bash -c 'bash "$SCRIPT"; echo $? > DONE' >> "$log" 2>&1 < /dev/null &
  echo $! > "$work/PID"
  stamp "started: $log"
}

case "${1:-}" in
  start)
    rm -rf "$work" && mkdir -p "$work"
    tar -C "$src" --exclude=./.wp --exclude=./runs -cf - . | tar -C "$work" -xf -
    parts=$(ls ${STATE:-/tmp/state/rl_state.tar.xz.*} 2>/dev/null)
    if [ -n "$parts" ]; then
      cat $parts | xz -dc | tar -C "$work" -xf - && stamp "unpacked $(echo $parts | wc -w) part(s) of the state"
    fi
    cd "$work" || exit
    python3 -m pip install -q --no-deps --no-build-isolation -e . > /dev/null 2>&1 || echo "editable install failed"
    nvidia-smi --query-gpu=name --format=csv,noheader
    launch
    ;;
  again)  # rl_ablation.sh once more in the same /tmp/run (e.g. STAGES=eval after the runs stopped)
    cd "$work" || exit
    launch
    ;;
  poll)
    if [ ! -f "$work/PID" ]; then  # a fresh host: the last one's run and files went with it
      echo "rl_remote: nothing was started in $work on this host (a host given back keeps no run): start again" >&2
      exit 3
    fi
    end=$((SECONDS + ${2:-540}))
    while [ $SECONDS -lt $end ] && [ ! -f "$work/DONE" ]; do
      if ! running; then
        sleep 1  # DONE is written just after the script ends
        [ -f "$work/DONE" ] || echo "rl_remote: $SCRIPT (pid $(cat "$work/PID")) is gone without an exit status (killed?)" >&2
        break
      fi
      sleep 5
    done
    [ -f "$work/DONE" ] && stamp "$SCRIPT ended with status $(cat "$work/DONE")"
    tail -n "${TAILN:-15}" "$log"
    progress
    nvidia-smi --query-gpu=utilization.gpu,memory.used --format=csv,noheader 2>/dev/null
    [ -n "${OUT:-}" ] && pack && send 0 "$OUT"
    ;;
  pack)
    pack && send 0 "${2:-${OUT:?pack needs a folder: \$2 or \$OUT}}"
    ;;
  send)  # the parts of the last pack from $2 on (what a command's ~64 MB left behind)
    send "${2:?send needs the first part, e.g. 4}" "${3:-${OUT:?send needs a folder: \$3 or \$OUT}}"
    ;;
  *)
    awk 'NR > 1 && !/^#/ {exit} NR > 1 {print}' "$0"; exit 2
    ;;
esac
