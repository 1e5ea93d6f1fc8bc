"""Simulated RealSense D455: scenes, ray casting, sensor effects, rendering into captures."""
