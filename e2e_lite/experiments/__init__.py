"""What the last chapters run on top of everything below: the safety module around a learned
driver, the ablation table of chapter 10, and replays of a drive."""
