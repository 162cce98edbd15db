"""Tables and their schemas, the checksummed stage cache and atomic files, the code fingerprint
that keys it, and how a job holds its variants' estimates."""
