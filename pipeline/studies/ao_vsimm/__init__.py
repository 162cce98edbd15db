"""Study 001 (spec 001-ao-vsimm): activation-only VSIMM against FSIMM and VSIMM on a 2-D maneuvering target."""
