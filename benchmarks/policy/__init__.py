"""A compact visuomotor policy and its closed-loop evaluation, for the policy-in-the-loop benchmark
(``python -m benchmarks policy_sim``): demonstrations read with ``manisplat.episode``, an
ACT-style action-chunking policy, and rollouts in the simulator's ``policy_env`` (in its own venv)."""
