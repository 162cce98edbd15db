"""Study 000's sensor is the shared 3-D radar (pipeline.sensors); this name stays for stored runs'
configs (``_target_: pipeline.studies.mie_los.sensor.Radar3D``)."""

from pipeline.sensors import Radar3D  # noqa: F401
