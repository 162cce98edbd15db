"""Study 002 (spec 002-async-bias): asynchronous multisensor bias estimation."""
