"""The bottom layer, imported by every other: the error tree (``errors``), how files are
opened and written (``files``), the samples a pipeline reads (``samples``) and their
spill to disk (``spill``), effect and equation identifiers (``effect_names``), DBC units
to SI (``units``), untrusted text in generated C (``c_escape``) and a call run in a thread
(``background``). It imports no other layer and no I/O package (python-can, cantools).
"""
