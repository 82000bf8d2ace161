"""The mathematics of the identification, free of I/O: samples in, parameters out.

The effect library and user expressions (``effects``, ``expr``), the state-variable
filter (``svf``), the model and its equations and regressors (``model``, ``equation``),
sample selection (``selection``), recursive least squares in float (``rls``) and in
fixed point (the ``fixed`` package, the target's specification), and the pipeline that
runs them per equation (``pipeline``, with ``settings`` and ``estimates``); physical
plausibility (``physics``) and how the residual's colour inflates sigma
(``sigma_inflation``). It imports only
:mod:`canrls.core` and no I/O package (python-can, cantools).
"""
