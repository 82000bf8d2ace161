"""canrls: identify the physics of an electric drive online, over CAN.

One folder per layer; dependencies run one way (docs/architecture.md)::

    core -> can | estimation -> processor -> diagnosis | live | firmware | fleet -> cli
                                                            (sim only at the edges)

The daemon (``canrls run``) and the offline replay (``canrls fit``) call the same
processor, so a replayed log gives the same parameters as the live run, bit for bit.
Their loops run in C extensions built at installation; importing canrls writes nothing.
The modules that moved into the layers' folders are still importable under their old
names for one release, with a :class:`DeprecationWarning` (:data:`MOVED`).
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.util
import sys
import warnings
from collections.abc import Sequence
from importlib.machinery import ModuleSpec
from types import ModuleType

from canrls.core.errors import CanrlsError

__version__ = "0.1.0"

__all__ = ["CanrlsError", "MOVED", "__version__"]

#: old module path -> new module path (issue 29: the folders are the layers, and no two
#: modules share a file name); the old paths go in the release after 0.1
MOVED = {
    "canrls.background": "canrls.core.background",
    "canrls.c_export": "canrls.firmware.kernel_export",
    "canrls.can.pairing": "canrls.processor.pairing",
    "canrls.can.period": "canrls.processor.period",
    "canrls.can.reorder": "canrls.processor.reorder",
    "canrls.can.times": "canrls.processor.times",
    "canrls.can.units": "canrls.core.units",
    "canrls.config": "canrls.processor.config",
    "canrls.control.settings": "canrls.control.tune_limits",
    "canrls.control.tune": "canrls.control.tuner",
    "canrls.ctext": "canrls.core.c_escape",
    "canrls.diagnosis.validate": "canrls.diagnosis.validation",
    "canrls.effect_names": "canrls.core.effect_names",
    "canrls.errors": "canrls.core.errors",
    "canrls.estimation.fixed.results": "canrls.estimation.fixed.trace",
    "canrls.estimation.fixed_formats": "canrls.estimation.fixed.formats",
    "canrls.estimation.fixed_kernels": "canrls.estimation.fixed.kernels",
    "canrls.estimation.fixed_layout": "canrls.estimation.fixed.layout",
    "canrls.estimation.fixed_plan": "canrls.estimation.fixed.plan",
    "canrls.estimation.fixed_results": "canrls.estimation.fixed.trace",
    "canrls.estimation.fixed_sweep": "canrls.estimation.fixed.sweep",
    "canrls.files": "canrls.core.files",
    "canrls.firmware.fit": "canrls.firmware.target_fit",
    "canrls.firmware.live": "canrls.firmware.target_live",
    "canrls.firmware.model": "canrls.firmware.target_model",
    "canrls.fleet.live": "canrls.fleet.live_appender",
    "canrls.fleet.report": "canrls.fleet.fleet_report",
    "canrls.live.bus": "canrls.live.bus_link",
    "canrls.live.history": "canrls.live.history_hook",
    "canrls.live.machine": "canrls.live.machine_daemon",
    "canrls.live.monitor": "canrls.live.monitor_listener",
    "canrls.live.settings": "canrls.live.daemon_settings",
    "canrls.modelfile": "canrls.processor.modelfile",
    "canrls.processor.results": "canrls.processor.fit_result",
    "canrls.replay": "canrls.processor.replay",
    "canrls.signals": "canrls.core.samples",
    "canrls.sim.bus": "canrls.sim.interface",
    "canrls.sim.fleet": "canrls.sim.fleet_plan",
    "canrls.spill": "canrls.core.spill",
    "canrls.target": "canrls.firmware",
    "canrls.target.cgen": "canrls.firmware.cgen",
    "canrls.target.export": "canrls.firmware.target_export",
    "canrls.target.fit": "canrls.firmware.target_fit",
    "canrls.target.load": "canrls.firmware.load",
    "canrls.target.model": "canrls.firmware.target_model",
    "canrls.target.qmath": "canrls.firmware.qmath",
    "canrls.target.spec": "canrls.firmware.spec",
    "canrls.target.tables": "canrls.firmware.tables",
    "canrls.target.vectors": "canrls.firmware.vectors",
}


class _MovedFinder(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Imports an old module path of :data:`MOVED` as the module at its new path."""

    def find_spec(self, fullname: str, path: Sequence[str] | None,
                  target: ModuleType | None = None) -> ModuleSpec | None:
        if fullname not in MOVED:
            return None
        return importlib.util.spec_from_loader(fullname, self)

    def create_module(self, spec: ModuleSpec) -> ModuleType | None:
        return None  # a placeholder; exec_module puts the real module in its place

    def exec_module(self, module: ModuleType) -> None:
        new = MOVED[module.__name__]
        warnings.warn(f"{module.__name__} is now {new}; the old name goes in the next "
                      f"release", DeprecationWarning, stacklevel=2)
        # the import system returns what sys.modules holds under the old name
        sys.modules[module.__name__] = importlib.import_module(new)


if not any(isinstance(f, _MovedFinder) for f in sys.meta_path):
    sys.meta_path.insert(0, _MovedFinder())
