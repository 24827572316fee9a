"""Running an experiment on a stage: play, record, calibrate, learn.

What belongs here: playing planned waveforms on a stage and scoring what it did
(:mod:`~afmctl.experiment.runner`, which also records sweeps), calibrating a stage from recorded
sweeps (:mod:`~afmctl.experiment.calibration`), and learning from repeated runs
(:mod:`~afmctl.experiment.learn`). A stage is any object with the interface of
:class:`afmctl.drivers.StageBase`, passed in: nothing here imports :mod:`afmctl.drivers` or opens
a device itself.
"""
