"""Which measurement kind (filters.base.MEASUREMENT_KINDS) a Stone Soup measurement model takes, by its type.

Known by name for Stone Soup's own classes, so the framework's compatibility check (before anything
is built) reads a variant's or a sensor's kind off its YAML without importing Stone Soup; a user's
subclass of one of them is imported and placed by its bases.
"""

from __future__ import annotations

from typing import Any, Mapping

# a Stone Soup measurement model's type (or a base of it) -> the measurement kind it takes
MODEL_KINDS = {
    "stonesoup.models.measurement.linear.LinearGaussian": "position_xy",
    "stonesoup.models.measurement.nonlinear.CartesianToElevationBearingRange": "range_azimuth_elevation",
}
# our measurement names per kind (the detections' measurement_names)
KIND_MEASUREMENTS = {"position_xy": ("x", "y"), "range_azimuth_elevation": ("range", "azimuth", "elevation")}


def kind_of_model(model: Any) -> str | None:
    """The measurement kind of a Stone Soup measurement model: an instance, a class or a dotted class name
    (``_target_``); its own type's or its nearest base's in MODEL_KINDS. None: no kind of this project
    (or a name that cannot be imported)."""
    if isinstance(model, str):
        if model in MODEL_KINDS:
            return MODEL_KINDS[model]
        try:
            from hydra.utils import get_object
            model = get_object(model)
        except Exception:  # noqa: BLE001 - the build reports a bad _target_ with its own message
            return None
    cls = model if isinstance(model, type) else type(model)
    for base in getattr(cls, "__mro__", ()):
        kind = MODEL_KINDS.get(f"{base.__module__}.{base.__qualname__}")
        if kind is not None:
            return kind
    return None


def model_target(config: Mapping, *paths: tuple[str, ...]) -> str | None:
    """The first ``_target_`` found at one of ``paths`` (key sequences) in a config node."""
    for path in paths:
        node: Any = config
        for key in path:
            node = node.get(key) if hasattr(node, "get") else None
            if node is None:
                break
        if node is not None and hasattr(node, "get") and node.get("_target_"):
            return str(node.get("_target_"))
    return None
