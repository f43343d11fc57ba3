"""lidar_obstacles: flight-obstacle and DEM extraction from airborne LiDAR for low-flying UAVs."""

__version__ = "0.1.0"
