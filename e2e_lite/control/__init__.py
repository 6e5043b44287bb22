"""Classical driving on top of the simulation: the trajectory format and the labels (affordances),
the LQR tracker, the rule-based expert, the oracle and the scripted drivers."""
