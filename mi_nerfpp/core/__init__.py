"""The rendering core: ray geometry of both volumes, sample placement, fields, quadrature and
the Eq. 4 composite, the model they make up, and the sizes a run may take (no file I/O, no
training)."""
