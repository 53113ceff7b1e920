"""The API's routers, one module per area (system, datasets, fits and models, diagnoses, targets)."""
