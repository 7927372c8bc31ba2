"""The simulator: scenarios and rendering of realistic recorded runs."""
