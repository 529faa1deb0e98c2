"""Renders of a trained model through the integrator: layered views, deep EXRs, videos, and
the scene files that render it."""
