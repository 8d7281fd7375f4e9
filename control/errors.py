"""The error type of :mod:`softbody.control`."""


class ControlError(ValueError):
    """Bad input to a loss, an optimiser or an estimator; the message names the problem and the fix."""
