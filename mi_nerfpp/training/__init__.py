"""Fitting a model to a dataset: the options, the losses and priors, the optimizer, the
training loop and held-out evaluation."""
