"""Text in, layout out: read an instruction and generate layouts for it (``physcene generate``).

``generate(instruction, generator=..., n=..., repair=..., out=...)`` returns a :class:`Generation`
of :class:`Sample` s; ``read_instruction`` is the reading alone (scene type, objects, counts,
relations, words not understood). Generators: ``procedural`` (offline), ``endpoint:URL``,
``model:PATH`` (docs/generate.md).
"""

from physcene.generation.instruction import Instruction, Mention, Relation, read_instruction
from physcene.generation.procedural import GenerationError, procedural_scene
from physcene.generation.samples import EXPORT_FORMATS, GENERATORS, Generation, Sample, generate

__all__ = [
    "EXPORT_FORMATS",
    "GENERATORS",
    "Generation",
    "GenerationError",
    "Instruction",
    "Mention",
    "Relation",
    "Sample",
    "generate",
    "procedural_scene",
    "read_instruction",
]
