"""Study scripts over evaluated layouts, each runnable as ``python -m physcene.eval.analysis.<name>``
and tested under tests/eval/ (docs/results.md cites what they measured)."""
