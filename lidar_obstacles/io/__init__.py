"""Input/output: PointCloud2 <-> NumPy, bags, LAS/LAZ, GeoTIFF. No rclpy."""
