"""LTC measurement station: configs, patterns, acquisition runs, LTC reconstruction, lens derivation, CLI."""
