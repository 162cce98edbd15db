"""Multi-target trackers (association, track management, GM-PHD) on the contract in ``base``."""

from filters.multitarget.base import POSITION_SETS, DetectionSets, MultiTargetTracker, TrackSets  # noqa: F401
