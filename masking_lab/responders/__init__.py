"""Who answers a 3IFC trial: a simulated observer, a terminal keypad, or a PsychoPy window."""
