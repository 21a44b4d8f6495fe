"""The database: every experiment, stage, parameter set θ, model ω and evaluation P."""
