"""The model: particle state, scenes and their validation, effects, accuracy settings, energy."""
