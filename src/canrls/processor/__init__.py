"""The front end shared by the live daemon and the offline replay.

``frames -> strict decode -> pairing -> samples -> calibration -> Pipeline``: the one
place that decides the signal ranges, the normalisation and the ridge prior's scale, by
one causal rule, so a log replayed offline gives the daemon's parameters bit for bit
(docs/architecture.md, "The calibration rule"). :class:`FrameProcessor` takes frames,
:class:`SampleProcessor` samples; a replay's result is a :class:`FitResult`.
"""

from canrls.estimation.settings import MIN_ENERGY, RMS_HEADROOM
from canrls.processor.calibration import (
    RESTORE_PERIOD_TOLERANCE,
    Calibration,
    RangeScanner,
    SampleProcessor,
    WindowScaling,
    calibrate,
    data_defaults,
    dbc_ranges,
    measure_noise,
    sample_period,
    scan_ranges,
)
from canrls.processor.fit_result import (
    AxisInfo,
    FileShift,
    FitResult,
    FrameCounts,
    PeriodInfo,
    StartInfo,
    TargetRun,
    epoch_date,
)
from canrls.processor.frames import SEEN_IDS, FrameProcessor

__all__ = ["AxisInfo", "Calibration", "FileShift", "FitResult", "FrameCounts", "FrameProcessor",
           "MIN_ENERGY", "PeriodInfo", "RESTORE_PERIOD_TOLERANCE", "RMS_HEADROOM", "RangeScanner",
           "SEEN_IDS", "SampleProcessor", "StartInfo", "TargetRun", "WindowScaling", "calibrate",
           "data_defaults", "dbc_ranges", "epoch_date", "measure_noise",
           "sample_period", "scan_ranges"]
