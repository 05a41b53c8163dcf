"""Network design: differentiable designs, design criteria, design optimisation."""
