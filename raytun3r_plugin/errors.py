"""The project's error hierarchy: every error raytun3r raises derives from :class:`Raytun3rError`."""

from __future__ import annotations


class Raytun3rError(Exception):
    """Base class of every error raised by raytun3r."""


class CameraError(Raytun3rError, ValueError):
    """A camera or calibration file is malformed, incomplete or outside the model's domain."""


class CameraModelError(CameraError, TypeError):
    """A camera model class is defined or used wrongly (the abstract base instantiated, or a
    subclass whose parameter names do not start with the four intrinsics)."""


class AdapterError(Raytun3rError, ValueError):
    """An adapter file or adapter object is corrupt, inconsistent or made for another model."""


class UnsupportedUpstreamError(Raytun3rError, TypeError):
    """The upstream model code does not have the structure a patch expects."""


class BackboneRegistrationError(Raytun3rError, ValueError):
    """A :class:`~raytun3r_plugin.registry.BackboneSpec` is inconsistent and cannot be registered."""


class DuplicateBackboneError(BackboneRegistrationError):
    """A backbone family, or a ``load_backbone`` name, is registered already."""


class AlreadyAppliedError(Raytun3rError, RuntimeError):
    """The model already carries a raytun3r patch with another camera or adapter."""


class NotAppliedError(Raytun3rError, RuntimeError):
    """``remove`` was asked for a model that carries no raytun3r patch."""


class InputError(Raytun3rError, ValueError):
    """Images or other run-time inputs do not fit the model or the camera."""


class DatasetError(Raytun3rError, ValueError):
    """A dataset folder or file is missing or malformed."""


class WeightsError(Raytun3rError, ValueError):
    """A weight file is missing, corrupt or does not match the network."""


class MissingDependencyError(Raytun3rError, ImportError):
    """An optional upstream package needed for the request is not installed."""


class PatchedCopyError(Raytun3rError, RuntimeError):
    """``copy.deepcopy`` was asked for a part of a patched model, or for a handle on its own."""


class SplitInstallError(Raytun3rError, ImportError):
    """``raytun3r_plugin`` and ``raytun3r_plugin.patches`` were imported from different source trees."""


class TaskError(Raytun3rError, RuntimeError):
    """A task run by :mod:`raytun3r_plugin.cluster` raised, or its worker died more often than
    it may be retried; the message names the task and its error."""


class BrowserError(Raytun3rError, RuntimeError):
    """Headless Chromium did not render a page: it did not start, answer or load it in time, or
    refused a DevTools request (``raytun3r report --png``, the report's browser test)."""


def require_module(module: str, extra: str, purpose: str):
    """Import the optional package ``module``, or raise :class:`MissingDependencyError` saying
    that ``purpose`` (e.g. "this export") needs it and which extra installs it."""
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError as error:
        raise MissingDependencyError(
            f"{purpose} needs the optional package {module!r} ({error}); install it with: "
            f"pip install 'raytun3r[{extra}]'"
        ) from error


class ClusterConnectionError(Raytun3rError, ConnectionError):
    """A Ray cluster named by ``--address`` could not be joined (after the retries a Ray Client
    connection gets); the message names the address and Ray's reason."""
