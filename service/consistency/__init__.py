"""Stack consistency: the stage between inference and the response that uses what one slice cannot know.

A single slice cannot tell its pose from its left-right twin, nor its own error from the motion
of the fetus; the slices of one stack together can (:mod:`service.consistency.stack_fit`). Where
slices of different stacks cross, their images must agree: that refines what the poses could not
(:mod:`service.consistency.image_refinement`, on :mod:`service.consistency.intersections`).
"""

from service.consistency.stack_fit import StackFit, fit_stack

__all__ = ["StackFit", "fit_stack"]
