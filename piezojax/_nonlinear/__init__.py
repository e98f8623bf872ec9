"""Continuous-time nonlinear models integrated with diffrax (Bouc-Wen oscillator, electromechanical actuator)."""
