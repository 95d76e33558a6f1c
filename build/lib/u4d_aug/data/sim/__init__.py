"""Built-in simulated 4D LiDAR world: procedural streets with moving agents, ray-cast with open3d, written as
SemanticKITTI sequences (`simulate`), and a realism report against real scans (`sim-report`)."""
