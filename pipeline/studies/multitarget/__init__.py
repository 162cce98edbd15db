"""The multi-target study (issue 41): births, deaths, misses and clutter; GNN, JPDA, GM-PHD and IMM
trackers (filters.multitarget) and Stone Soup's scored with GOSPA over Monte Carlo runs."""
