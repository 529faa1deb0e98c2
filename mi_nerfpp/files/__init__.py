"""The files a model and its renders are kept in: atomic writes, checkpoints, layered EXRs, PNG
previews."""
