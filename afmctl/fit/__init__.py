"""Fitting and judging the model: what afmctl learns from measured sweeps, and how well.

What belongs here: identification of a model from sweeps (:mod:`~afmctl.fit.identify`, its
parametrization and multi-start, the noise floor, the uncertainty of the fit, the baselines a fit
is compared with), and diagnosis of what a fit gets wrong (:mod:`~afmctl.fit.diagnose`: the
catalogue of candidate causes in :mod:`~afmctl.fit.candidates`, their joint fits in
:mod:`~afmctl.fit.extension`, the verdict rules in :mod:`~afmctl.fit.verdict`, sensor-side causes
and their actuator-side twins in :mod:`~afmctl.fit.twins`, the residual analysis in
:mod:`~afmctl.fit.residuals`, the report in :mod:`~afmctl.fit.diagnosis_report`), and whether the
sweeps' minor loops close (:mod:`~afmctl.fit.closure`). Pure numerics on sweeps already read: no
device I/O and no plotting.
"""
