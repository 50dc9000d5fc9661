"""The recipe a new robot gets: a config file written from a LeRobot set's own feature names and
the diagnosis of its data (`pi0_armfix.tools.write_config`, docs/data.md "Any other LeRobot
dataset").

  naming     the action vector's groups and roles proposed from its dims' names
  evidence   what the data says per dim: binary (a gripper), where the state holds the same
             joint, position or velocity command (the finite-difference test)
  recipe     the proposal as one value: layout, state map, cameras, split, and the lever the
             mechanism verdicts name, each with the reason it was chosen
  render     the recipe as a config file that `train` takes as is
"""
