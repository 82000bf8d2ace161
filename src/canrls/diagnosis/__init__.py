"""The diagnosis layer: where the model fails and which effect is missing.

Entry points in :mod:`canrls.diagnosis.analysis` (:func:`~canrls.diagnosis.analysis.diagnose`,
:func:`~canrls.diagnosis.analysis.diagnose_log`); the modules, lowest first:

``results``     the result values (plain frozen dataclasses with ``to_dict``)
``record``      the record as the pipeline sees it: its sample policy, gap filling,
                restarts, used rows and columns
``residual``    statistics of the residual: whiteness, bins, regions, order spectrum,
                excitation, structure left
``candidates``  candidate effects, ranking, forward selection, identifiability, verdict
``figures``     the SVG figures (matplotlib, optional)
``report``      the report object; text, JSON and the HTML page (``templates/``, jinja2)
``analysis``    the entry points: run the pipeline, put the diagnosis together
"""
