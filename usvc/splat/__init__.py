"""3D Gaussian splatting: the per-scene model that renders new views for the training buffer."""
