"""drivectl: a drive controller for ball-screw feed axes (CiA 402 over CANopen, with a plant emulator)."""

__version__ = "0.1.0"


def connect(config=None, **kwargs):  # noqa: ANN001, ANN003, ANN201 - the signature is drivectl.session.connect's
    """Connect to a machine and hold its axes under the resident loop: see :func:`drivectl.session.connect`."""
    from drivectl.session import connect as _connect

    return _connect(config, **kwargs)
