"""The world simulator: floor plan and ray casting, the robot, the camera renderer, the sensor error model."""
