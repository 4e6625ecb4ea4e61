"""Benchmark data: synthetic MesaTask-style scenes, noise, instructions, MesaTask-CTRC construction."""
