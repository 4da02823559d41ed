"""The wear-life method (METHOD.md): pure, no I/O, no clock."""
from .core import (
    Result,
    SlotArrays,
    SlotOut,
    StreamingMonitor,
    analyze_readings,
    analyze_slots,
    gate_arrays,
    run_streaming,
    to_slots,
)
from .forecast import Forecaster, ForecastOut, PriorForecast, prior_forecast
from .params import PARAM_NAMES, PARAMS, RESULT_KEYS, MethodParams, ParamError, build_params
from .start import StartOutcome, StartSequence
from .wear import WearTracker, WindowOut

__all__ = [
    "MethodParams", "ParamError", "PARAMS", "PARAM_NAMES", "RESULT_KEYS", "build_params",
    "Result", "SlotArrays", "SlotOut", "StreamingMonitor", "analyze_readings", "analyze_slots",
    "gate_arrays", "run_streaming", "to_slots", "StartOutcome", "StartSequence", "WearTracker",
    "WindowOut", "Forecaster", "ForecastOut", "PriorForecast", "prior_forecast",
]
