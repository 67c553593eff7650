"""Task-oriented alignment: Motion/Skill phases, keypoint tracking, hybrid pseudo-ground-truth poses."""
