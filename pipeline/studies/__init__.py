"""One package per study: its scenario, sensor, adapter (pipeline.contract.Study), table codecs,
recording, printed tables and reproduction targets. Shared modules name no study."""
