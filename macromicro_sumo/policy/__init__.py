"""Stage II: the shared policy and its PPO training."""
