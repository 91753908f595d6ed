"""SimVehicle with real ground-station tools (a package: test names here cannot clash with other
directories' test_sim_*.py)."""
