"""Readers of the camera/image layouts people capture and download, one module per format."""
