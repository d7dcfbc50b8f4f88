"""Model checking: compare measurements with the model's predictions, localize the failures,
rank and fit the missing effects."""
