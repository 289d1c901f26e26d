"""File formats: C3D, video, OpenPose/COCO JSON, CHI3D JSON, MCAP."""
