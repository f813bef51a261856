"""The grasp choice: features of the haptic history at the decision point, counterfactual labels
from snapshot-and-branch, the selector and the failure predictor.

Empty for now; the grasp-choice code goes here, one module per concept.
"""
