#!/bin/bash
# snapshot.sh RUN DEST [ROOT]: copy a running PADA job's newest complete checkpoint (one with a
# trainer_state.json, which the Trainer writes after the weights and the optimizer, so a checkpoint
# being written is skipped) to DEST as snapshot.tar.xz.* parts under 16 MiB, its paths relative to
# ROOT (default /tmp/run, where pada_run.sh runs), and its log history as DEST/snapshot_train_log.json.
# A machine taken back mid-run then leaves the steps of the last poll: `cat snapshot.tar.xz.* >
# .wp/ckpt.tar.xz` and the next pada_run.sh resumes from it.
run=${1:-/tmp/run/runs/small/pada}; dest=${2:-${OUT:-}}; root=${3:-/tmp/run}
[ -d "$run" ] && [ -n "$dest" ] || exit 0
run=$(cd "$run" && pwd); root=$(cd "$root" && pwd)
case "$run" in "$root"/*) ;; *) echo "snapshot: $run is not under $root" >&2; exit 2 ;; esac
last=""
for d in $(ls -d "$run"/checkpoint-* 2>/dev/null | sort -t- -k2 -n); do
  [ -f "$d/trainer_state.json" ] && last=$d
done
[ -n "$last" ] || { echo "snapshot: no complete checkpoint in $run yet"; exit 0; }
relative=${run#"$root"/}
tmp=$(mktemp -d); mkdir -p "$tmp/$relative"
cp -a "$last" "$tmp/$relative/" || { rm -rf "$tmp"; exit 0; }
cp "$run"/physcene_run.json "$dest"/snapshot_run.json 2>/dev/null
python3 -c "import json,sys; json.dump(json.load(open(sys.argv[1]))['log_history'], open(sys.argv[2], 'w'), indent=1)" \
  "$tmp/$relative/$(basename "$last")/trainer_state.json" "$dest/snapshot_train_log.json"
rm -f "$dest"/snapshot.tar.xz.*
tar -C "$tmp" -cf - "${relative%%/*}" | xz -1 -T0 | split -b 15M - "$dest/snapshot.tar.xz."
rm -rf "$tmp"
echo "snapshot: $(basename "$last") -> $(ls "$dest" | grep -c '^snapshot.tar.xz') part(s)"
