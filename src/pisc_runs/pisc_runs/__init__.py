"""PISC runs: a run's verdict and summary, analysis and plots, the rig drawn (markers, animation, Foxglove live view), playing a bag and replaying it through the controllers' cores."""
