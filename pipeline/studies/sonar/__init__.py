"""Study 003 (spec 003-sonar-mgekf): active/passive sonar tracking with the modified gain EKF."""
