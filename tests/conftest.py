"""Fixtures shared by the test modules, and the one place that decides what runs.

Markers (pyproject's ``[tool.pytest.ini_options]``): ``cuda`` tests skip without a CUDA device;
``slow`` tests skip unless asked with ``--slow`` or ``PHYSCENE_SLOW=1``.
"""

import functools
import os
import sys
from pathlib import Path

import pytest

# Test modules import shared strategies and fixtures from each other by basename (``from test_ctrc
# import layouts``); basenames are unique across tests/, so every test folder is importable.
for _folder in sorted(p for p in Path(__file__).resolve().parent.iterdir() if p.is_dir()):
    if not _folder.name.startswith((".", "_")) and str(_folder) not in sys.path:
        sys.path.insert(0, str(_folder))


def pytest_addoption(parser):
    parser.addoption("--slow", action="store_true", default=False, help="also run tests marked slow")


@functools.cache
def _has_cuda() -> bool:
    import torch

    return torch.cuda.is_available()


def pytest_collection_modifyitems(config, items):
    slow = config.getoption("--slow") or os.environ.get("PHYSCENE_SLOW") == "1"
    for item in items:
        if "cuda" in item.keywords and not _has_cuda():
            item.add_marker(pytest.mark.skip(reason="needs a CUDA device"))
        if "slow" in item.keywords and not slow:
            item.add_marker(pytest.mark.skip(reason="slow: run with --slow or PHYSCENE_SLOW=1"))


@pytest.fixture
def step_counter():
    """A factory of Trainer callbacks that record the step a run began at and count its optimizer
    steps (to see that a resumed run takes only the steps not yet taken)."""
    from transformers import TrainerCallback

    class StepCounter(TrainerCallback):
        def __init__(self):
            self.begin, self.steps = None, 0

        def on_train_begin(self, args, state, control, **kw):
            self.begin = state.global_step

        def on_step_end(self, args, state, control, **kw):
            self.steps += 1

    return StepCounter


@pytest.fixture(scope="session")
def written_into():
    """``written_into(dx_cm)`` -> (clean, colliding): the first level-2 scene of the test split's plan,
    and the same with its last table-level object written ``dx_cm`` beside its first one along x (a
    collision the reward charges to the later-written object)."""
    from physcene.data.benchmark import DataConfig, build_scenes
    from physcene.data.splits import plan_split
    from physcene.scene import TABLE

    item = next(i for i in plan_split("test", 40, 0) if i.level == 2)
    clean = build_scenes("test", 0, item, DataConfig())[0]
    table = [o for o in clean.objects if o.parent == TABLE]
    first, last = table[0], table[-1]

    def collide(dx_cm: float):
        return clean, clean.with_objects(
            o.moved(center=(first.center[0] + dx_cm, first.center[1], o.center[2])) if o is last else o
            for o in clean.objects)

    return collide


@pytest.fixture(scope="session")
def generated():
    """``generated(tokenizer, texts)`` -> ``{"completion_ids", "completion_mask"}``: the texts as TRL hands
    PADA its rollouts, each tokenized, ended with EOS and right-padded to the longest."""
    import torch

    def rollouts(tokenizer, texts):
        rows = [tokenizer(t, add_special_tokens=False)["input_ids"] + [tokenizer.eos_token_id] for t in texts]
        width, pad = max(map(len, rows)), tokenizer.pad_token_id
        return {"completion_ids": torch.tensor([r + [pad] * (width - len(r)) for r in rows]),
                "completion_mask": torch.tensor([[1] * len(r) + [0] * (width - len(r)) for r in rows])}

    return rollouts
