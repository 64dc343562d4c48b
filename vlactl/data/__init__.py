"""Datasets: scripted-expert demonstrations and LeRobot-format reading/writing."""
