"""The guided compass calibration (every compass at once) and what follows it.

* ``core.CalibrationWizard`` — the dance, per-compass results and the after-write state.
* ``progress`` (net turn about the step's axis), ``coverage`` (directions seen, next pose),
  ``compass`` (one compass's samples and live fit), ``fit`` (final fit, orientation),
  ``quality`` (fitness, reasons in words), ``consistency`` (compasses against each other),
  ``onboard`` (the vehicle's own calibrator), ``largevehicle`` (fixed-yaw calibration),
  ``aftercheck`` (heading check, deviation card), ``texts`` (what the page says),
  ``settings`` (thresholds).
"""
from groundstation.station.wizard.core import MODES, WIZARD_STEPS, CalibrationWizard
from groundstation.station.wizard.settings import DEFAULT_SETTINGS, FITNESS_LEVELS, WizardSettings

__all__ = ["CalibrationWizard", "WizardSettings", "DEFAULT_SETTINGS", "FITNESS_LEVELS", "WIZARD_STEPS", "MODES"]
