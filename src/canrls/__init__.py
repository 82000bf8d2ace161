"""canrls: identify the physics of an electric drive online, over CAN.

The package is layered so that dependencies run one way::

    bus, codec, log readers (edges)  ->  pipeline (pure)  <-  effects, model, rls, fixed

The daemon (``canrls run``) and the offline replay (``canrls fit``) call the same
pipeline, so a replayed log gives the same parameters as the live run, bit for bit.
Their loops run in C extensions built at installation; importing canrls writes nothing.
"""

from __future__ import annotations

from canrls.errors import CanrlsError

__version__ = "0.1.0"

__all__ = ["CanrlsError", "__version__"]
