"""physcene: physically consistent tabletop scene generation (PhyScene3D: CTRC + PADA).

Data flows one way: text -> ``ctrc.parse`` -> ``Scene`` -> ``physics`` -> scores/gradients ->
``tto`` -> ``Scene`` -> export / eval. See docs/ and DESIGN.md.
"""

from physcene.scene import TABLE, Scene, SceneError, SceneObject, Zone

__version__ = "0.1.0"
__all__ = ["TABLE", "Scene", "SceneError", "SceneObject", "Zone", "__version__"]
