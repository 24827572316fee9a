"""The physics: the paper's model of a piezo stage, pure functions and frozen parameter sets.

What belongs here: the homogenized energy model of the polarization (Algorithm 1, the thermal
kernel (6)-(10), the densities of (11)-(13): :mod:`~afmctl.model.hysteresis`), the lumped rod
(16)/(17) (:mod:`~afmctl.model.rod`), the transducer that composes them with the effects of a real
stage (amplifier, gauge, second mode: :mod:`~afmctl.model.transducer`,
:mod:`~afmctl.model.effects`), and the inverses, Algorithms 2 and 3
(:mod:`~afmctl.model.inverse`). Nothing here reads a file, talks to a device or draws; nothing here
imports another room of afmctl except :mod:`afmctl.errors`.
"""
