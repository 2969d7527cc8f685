"""The trained models democheck ships, one folder each (config.json, model.safetensors, README.md): package data."""
