"""Algorithms: pure NumPy / SciPy / scikit-learn. Never imports rclpy or message packages."""
