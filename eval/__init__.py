"""Evaluation harness (installed as ``physcene.eval``): metrics, judges, renders, reports."""
