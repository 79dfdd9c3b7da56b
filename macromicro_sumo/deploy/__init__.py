"""Stage III: every method deployed population-wide on the scenario's own demand."""
