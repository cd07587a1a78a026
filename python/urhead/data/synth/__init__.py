"""Synthetic subjects with exact ground truth: a procedural head's look (:mod:`.scene`),
its motion and tracking noise (:mod:`.motion`), Loop subdivision (:mod:`.subdivision`),
the CPU ray tracer's Python side (:mod:`.raytrace`), and the subject they make
(:mod:`.subject`, ``urhead synth``)."""

from urhead.data.synth.subject import SynthConfig, synthesize

__all__ = ["SynthConfig", "synthesize"]
