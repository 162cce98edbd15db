"""Study 000 (spec 000-mie-los): modified input estimation, inertial vs decoupled line-of-sight filters."""
