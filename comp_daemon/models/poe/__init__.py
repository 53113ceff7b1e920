"""The product-of-exponentials model kind: seed 002's 12-error calibration (``calibration``),
the full twist-error chain (``twist``) and the error model with its fit and its registry entry
(``model``).
"""
