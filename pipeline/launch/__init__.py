"""What Hydra calls around the jobs: the folder check and sweep-summary callbacks, the job
log tag, a parameter search's objective."""
