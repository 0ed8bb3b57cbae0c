"""govnesf: mapper/model package."""
