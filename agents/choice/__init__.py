"""The grasp choice: features of the haptic history at the decision point, counterfactual labels
from snapshot-and-branch, the selector and the failure predictor.

Entry points: `policy.GraspChoicePolicy` (probe, decide, grasp; a pickle-free policy file that
`bh8 eval` and `bh8 deploy` load) and `trainer.ChoiceTrainer` (`bh8 train` with `algorithm =
"GraspChoice"`). Its parts: `features` (`ChoiceFeatures`: what the choice decides from, computed
from the feedback blocks), `labels` (which candidate grasps hold, by snapshot and branch) and
`model` (`SuccessModel`: each grasp's chance to hold) and `decision_env` (`DecisionEnv`: one
decision per episode, for RL over the discrete choice). Nothing is imported here, so importing one
module costs only it.
"""
