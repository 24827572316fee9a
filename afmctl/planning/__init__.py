"""Planning what is sent: the waveforms a stage plays, before anything moves.

What belongs here: desired trajectories (triangle, sine, from a file) and their Algorithm-3 plans
through the model with the paper's linear filter beside them, the validity envelope and the scores
of a run (:mod:`~afmctl.planning.track`); the learning law that corrects a waveform from a measured
run (:mod:`~afmctl.planning.ilc`); the sweep set designs used to identify a stage
(:mod:`~afmctl.planning.sweepdesign`). Pure numerics: no I/O.
"""
