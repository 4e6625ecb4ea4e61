"""Study scripts over trained checkpoints, each runnable as ``python -m physcene.train.analysis.<name>``
and tested under tests/train/. They load models through physcene.train, so they live here rather than
under eval/analysis/ (eval never imports physcene.train; docs/design.md)."""
