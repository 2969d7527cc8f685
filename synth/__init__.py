"""The suite recipes democheck ships (``democheck synth NAME``): package data."""
