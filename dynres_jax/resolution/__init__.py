"""Adaptive resolution (paper Sec. IV-C): ``bo``, Bayesian optimisation of ω per scene (the labels), and
``regressor``, g(y_0, y_g) -> ω, trained on them (``learn.regressor``) and read by the adaptive chooser."""
