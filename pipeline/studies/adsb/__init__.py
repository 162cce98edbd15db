"""Study on real ADS-B trajectories (issue 17): recorded flights of maneuvering aircraft as truths.

reading: the OpenSky/traffic column schema from Parquet, CSV or JSON(.gz), and the cleaning real
data need; flight: a truth in a radar site's ENU frame, RTS-smoothed and resampled to the scan
period, with maneuver labels; scenario: ``RecordedFlight``, the scenario node. samples/: the flights
shipped with the project (PROVENANCE.md); the others of traffic 2.13 with the ``adsb`` extra.
"""
