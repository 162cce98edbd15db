"""Stone Soup (the [stonesoup] extra, stonesoup 1.9.1) inside this project, and our runs as Stone Soup objects.

- ``pipeline.stonesoup.variant.StoneSoupFilter``: a filter variant built from Stone Soup components
  named in YAML (a transition model, a measurement model, a predictor, an updater; optionally an
  initiator or a prior). It filters one Monte Carlo run at a time (Stone Soup works on objects),
  spread over worker processes, and returns the TrackEstimate our filters return.
- ``pipeline.stonesoup.simulate.StoneSoupScenario`` / ``StoneSoupSensor``: a Stone Soup ground-truth
  simulator and detection simulator as the scenario and measure stages (our truth and detections
  tables, cached like any stage).
- ``pipeline.stonesoup.load.load_run``: a stored run (one of its Monte Carlo runs) as Stone Soup
  ground-truth paths, detections with their measurement models, and tracks, for Stone Soup's metric
  generators and plotters.

Why a package of ``pipeline`` and not a module of ``filters``: ``filters`` is batched numpy math with
no dependency beyond numpy and scipy; this is an adapter to an optional third-party library (one
object per run, processes), and its simulators and loader make and read ``pipeline.data`` tables.
Every module here imports Stone Soup only when used, so the classes can be looked up (the
framework's measurement-kind check, conf/filter listings) on an install without the extra.
"""

INSTALL_HINT = "pip install -e '.[stonesoup]'"


def require_stonesoup() -> None:
    """Import Stone Soup, or raise ImportError saying which extra brings it."""
    try:
        import stonesoup  # noqa: F401
    except ImportError as exc:
        raise ImportError(f"Stone Soup is not installed ({exc}); it comes with the [stonesoup] extra: "
                          f"{INSTALL_HINT}") from exc
