"""The foreign stage: a plant written independently of afmctl's model code.

Other formulas, other parameters and other sweep designs than afmctl's own (its hysteresis kernel
in :mod:`~afmctl.drivers.device.foreign.kernel`, the stage in
:mod:`~afmctl.drivers.device.foreign.stage`, hidden effects of other physics in
:mod:`~afmctl.drivers.device.foreign.effects`, random stages and sweep sets in
:mod:`~afmctl.drivers.device.foreign.stages` and :mod:`~afmctl.drivers.device.foreign.sweeps`,
and the emulator's physics on it in :mod:`~afmctl.drivers.device.foreign.physics`). Two-axis
stages: :mod:`~afmctl.drivers.device.foreign.xy_stage` (coupled by formulas of their own, with
the truth for scoring), their actuators in :mod:`~afmctl.drivers.device.foreign.xy_actuator` and
their sweep sets in :mod:`~afmctl.drivers.device.foreign.xy_sweeps`. Every numerical
capability of afmctl is shown on these stages, so that no test fits data made by its own code.
"""
