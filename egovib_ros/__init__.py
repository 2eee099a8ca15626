"""egovib_ros: ego-vibration removal for robot accelerometers by spectral subtraction."""

__version__ = "0.1.0"
