"""The runtime step: the bank (Kalman filters, LQ gains, blending, moving
bank) and the PI force loop, from a design artifact; allocation-free."""
