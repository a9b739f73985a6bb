"""Thin rclpy adapters around the core library: parameters, topics, services, message conversion."""
