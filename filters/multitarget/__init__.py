"""Multi-target trackers (association, track management, GM-PHD) on the contract in ``base``:
``trackers`` (GNN, JPDA, IMM-GNN, IMM-JPDA with M-of-N track management), ``gmphd`` (GM-PHD),
``metrics`` (GOSPA, OSPA, track-level measures); their parts in ``motion``, ``association`` and the
compiled ``kernel``. Import them from their modules (this package imports only the contract)."""

from filters.multitarget.base import POSITION_SETS, DetectionSets, MultiTargetTracker, TrackSets  # noqa: F401
