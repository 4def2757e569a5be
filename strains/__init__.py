"""skinmap.strains: resistances → calibrated strains (the gauge law, one definition both ways),
the tare and the mold calibration file.

- :mod:`~skinmap.strains.gauges`: :class:`Calibration`, the gauge law
  (:func:`gauge_resistance`, :func:`gauge_strain`), :func:`resistances_to_strains`, the
  mapping to nominal layer offsets and the rejection of impossible units (pure numpy);
- :mod:`~skinmap.strains.calfiles`: the tare and calibration files (format, atomic writes,
  loading with errors that name the file).
"""
from __future__ import annotations

from skinmap.strains.calfiles import (CALIBRATION_FORMAT, MAX_TARE_BYTES, calibration_path, compute_tare,
                                      load_calibration_file, load_tare, parse_calibration, parse_tare,
                                      save_calibration, save_tare, tare_path)
from skinmap.strains.gauges import (GAUGE_LENGTH_MM, HYSTERESIS_GAIN_SD, HYSTERESIS_LOOP, HYSTERESIS_LOOP_SD,
                                    MAX_PLAUSIBLE_STRAIN, MAX_UNIT_TURNING_RAD, RELAXATION_SHARE, RESPONSE_LAG_S,
                                    RESPONSE_TIME_S, SHARED_GAIN_SD,
                                    Calibration,
                                    cell_axes, cell_bending, cell_centres, gauge_resistance, gauge_strain, grid_size,
                                    reject_implausible_units, resistances_to_strains, response_lag_s,
                                    to_nominal_offsets,
                                    turning_noise_rad)

__all__ = ["CALIBRATION_FORMAT", "MAX_TARE_BYTES", "calibration_path", "compute_tare", "load_calibration_file",
           "load_tare", "parse_calibration", "parse_tare", "save_calibration", "save_tare", "tare_path",
           "GAUGE_LENGTH_MM", "HYSTERESIS_GAIN_SD", "HYSTERESIS_LOOP", "HYSTERESIS_LOOP_SD", "MAX_PLAUSIBLE_STRAIN",
           "MAX_UNIT_TURNING_RAD", "RELAXATION_SHARE", "RESPONSE_LAG_S", "RESPONSE_TIME_S",
           "SHARED_GAIN_SD", "Calibration", "cell_axes",
           "cell_bending", "cell_centres", "gauge_resistance", "gauge_strain", "grid_size", "reject_implausible_units",
           "resistances_to_strains", "response_lag_s", "to_nominal_offsets", "turning_noise_rad"]
