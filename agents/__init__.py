"""bh8_gym.agents: training, evaluation, scripted baselines, export and deployment of grasp policies (installed from agents/)."""
