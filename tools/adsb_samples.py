"""Convert traffic 2.13's sample flights to the Parquet files shipped in pipeline/studies/adsb/samples/.

Why: the study and CI must work without the 1.1 GB traffic install; a few flights, unmodified rows
in file order (so the cleaning counts are those of the original), in the OpenSky column schema.

    python tools/adsb_samples.py SAMPLES_DIR   # traffic/data/samples of an installed traffic 2.13,
                                               # or of its wheel unpacked (a zip)
"""

from __future__ import annotations

import sys
from pathlib import Path

import polars as pl

from pipeline.studies.adsb.reading import SAMPLES_DIR, read_opensky_table

# traffic sample (category/name) -> rows kept (None: all). Every flight is shipped whole.
SHIPPED = {
    "military/aircraft_carrier": None,
    "featured/zero_gravity": None,
    "featured/belevingsvlucht": None,
    "ambulances/rega_sg": None,
    "calibration/munich": None,
    "gliders/sisteron": None,
    "noisy/noisy_spoofing": None,
    "noisy/noisy_time_issue": None,
}
SCHEMA = {"timestamp": pl.Int64, "icao24": pl.String, "callsign": pl.String, "latitude": pl.Float64,
          "longitude": pl.Float64, "altitude": pl.Float64, "groundspeed": pl.Float64, "track": pl.Float64,
          "vertical_rate": pl.Float64, "onground": pl.Boolean}


def convert(samples: Path, out: Path = SAMPLES_DIR) -> None:
    out.mkdir(parents=True, exist_ok=True)
    for sample in SHIPPED:
        frame = read_opensky_table(samples / f"{sample}.json.gz")
        frame = frame.select([pl.col(c).cast(t) for c, t in SCHEMA.items() if c in frame.columns])
        target = out / f"{sample.rsplit('/', 1)[1]}.parquet"
        frame.write_parquet(target, compression="zstd", compression_level=19, statistics=False)
        print(f"{sample}: {frame.height} rows, {target.stat().st_size} bytes -> {target}")


if __name__ == "__main__":
    convert(Path(sys.argv[1]))
