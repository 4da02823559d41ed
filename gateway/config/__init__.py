"""Station configuration: ``load_station(path)``, ``load_fleet(folder)``, ``ConfigError``.

The schema — every key, its type, default, unit, allowed values and documentation — is one
declarative definition in :mod:`gateway.config.sections`; validation (:mod:`.loader`) and
``docs/configuration.md`` (:mod:`.docs`) are generated from it.
"""
from .loader import (
                     ConfigError,
                     Issue,
                     Loaded,
                     cross_issues,
                     fleet_file_for,
                     load_fleet,
                     load_station,
                     station_files,
                     validate_fleet,
                     validate_station,
)
from .sections import StationConfig

__all__ = ["ConfigError", "Issue", "Loaded", "StationConfig", "cross_issues", "fleet_file_for",
           "load_fleet", "load_station", "station_files", "validate_fleet", "validate_station"]
