"""democheck: audit robot demonstration datasets with PETNet task uncertainty."""

__version__ = "0.1.0"
