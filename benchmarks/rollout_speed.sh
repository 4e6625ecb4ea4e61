#!/bin/bash
# The rollout-speed figures of docs/training.md ("Generation speed") on one GPU, each part a JSON file in
# OUT (default runs/rollout_speed): every figure side by side with HF generate in the same process.
#
#   bash benchmarks/rollout_speed.sh [OUT]                     # every part, ~20 minutes on an H100
#   PARTS="exact pada_natural" bash benchmarks/rollout_speed.sh  # some of them
#   MODEL=runs/small/sft bash benchmarks/rollout_speed.sh       # another trained base (default: small-sft)
#
# Parts:
#   forced        random weights, 512 x 2048 forced tokens: HF static, fast, fast+cudnn, fast+fused+cudnn
#   trained       the trained base, rows stopping at EOS, compared up to it: HF static, fast, fast+fused+cudnn
#   exact         HF static and fast+cudnn, both with torch's cuDNN attention allowed (same kernel: same ids?)
#   exact_forced  the same pair on random weights, 512 x 2048 forced tokens (the acceptance's setting)
#   constrained   the trained base under the CTRC constraint: fast, fast+fused+cudnn
#   pada_forced   whole PADA steps, random weights, rollouts forced to 2,304 tokens: fast, fast+fused+cudnn
#   pada_natural  whole PADA steps from the trained base, rollouts of the lengths it writes (at most 2,304),
#                 the last step profiled (OUT/pada_<cache>.txt)
#   pada_switches whole PADA steps at the RL runs' settings (the trained base under the constraint, T = 0.7,
#                 merged adapters): the anchors' own pass or the joint one, PEFT's adapter input cast or not
#   pada_compiled whole PADA steps as pada_switches with the joint pass: the update's forwards eager or compiled
#                 (pada.compile_update; the warm-up step pays the compile, 4-7 minutes), without and with the
#                 constraint, then 10 compiled steps under the constraint
set -euo pipefail
OUT=${1:-runs/rollout_speed}
MODEL=${MODEL:-small-sft}
PARTS=${PARTS:-"forced trained exact exact_forced constrained pada_forced pada_natural pada_switches pada_compiled"}
mkdir -p "$OUT"
want() { [[ " $PARTS " == *" $1 "* ]]; }
gen="physcene bench generate --device cuda --batch 512 --tokens 2048 --repeat 1"
pada="physcene bench pada --device cuda --config small --tokens 2304 --steps 2 --json"

want forced && $gen --config small --variants static fast fast+cudnn fast+fused+cudnn --out "$OUT/forced.json"
want trained && $gen --model "$MODEL" --until-eos --variants static fast fast+fused+cudnn --out "$OUT/trained.json"
want exact && $gen --model "$MODEL" --until-eos --cudnn-attention --variants static fast+cudnn \
  --out "$OUT/exact_cudnn.json"
want exact_forced && $gen --config small --cudnn-attention --variants static fast+cudnn \
  --out "$OUT/exact_cudnn_forced.json"
want constrained && $gen --model "$MODEL" --constrained --variants fast fast+fused+cudnn --out "$OUT/constrained.json"
want pada_forced && $pada --caches fast fast+fused+cudnn --profile "$OUT/forced" > "$OUT/pada_forced.json"
want pada_natural && $pada --model "$MODEL" --until-eos --caches fast+fused+cudnn --profile "$OUT" \
  > "$OUT/pada_natural.json"
want pada_switches && $pada --model "$MODEL" --until-eos --constrained --caches fast+fused+cudnn --merge-adapters on \
  --joint-anchor-pass off on --adapter-input-cast on off --set pada.temperature=0.7 > "$OUT/pada_switches.json"
if want pada_compiled; then
  compiled="$pada --model $MODEL --until-eos --caches fast+fused+cudnn --merge-adapters on --joint-anchor-pass on \
    --set pada.temperature=0.7"
  for c in "" --constrained; do  # side by side, 3 timed steps each
    $compiled $c --steps 3 --compile-update off on > "$OUT/pada_compiled${c:+_constrained}.json"
  done
  # the constrained step swings with its rollouts: 10 timed steps of the compiled one
  $compiled --constrained --steps 10 --compile-update on > "$OUT/pada_compiled_constrained_10.json"
fi
echo "figures in $OUT"
