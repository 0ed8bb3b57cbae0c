"""govnesf: clients/sim package."""
