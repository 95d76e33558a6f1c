"""SemanticKITTI / nuScenes readers and writers, sensors, datasets and the simulated world."""
