"""fitting: end-to-end calibration of piezojax models by nonlinear least squares."""
