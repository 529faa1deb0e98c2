"""The error of a training run that cannot go on."""


class TrainingError(RuntimeError):
    """Training cannot go on (diverged, bad data for a step, or a resume that does not
    match)."""
