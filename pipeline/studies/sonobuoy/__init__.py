"""Study 004 (spec 004-ammpf-sonobuoy): auxiliary multiple-model particle filter for sonobuoys."""
