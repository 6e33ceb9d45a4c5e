"""The decision protocol every method shares: decisions on held-out training views, never
on the ground truth or the test views.

Layer: above ``core``, ``data`` and ``evaluation``, below the methods (``classical``,
``training``) that call it.

- ``split``: which training views are held out (``holdout_split``) and the check that
  enough remain on both sides (``decision_split``);
- ``early_stop``: the held-out-PSNR stop rule (``EarlyStopper``) and its defaults
  (``STOP_RULE``);
- ``discrepancy``: the noise level measured on held-out residuals and the discrepancy
  principle (Morozov);
- ``search``: a 1-D search over a regularisation weight on a log grid that widens until
  its choice is interior;
- ``heldout``: "decide on the fitted views, then run the decision on all views"
  (``run_heldout``; iterative classical methods);
- ``views``: the same idea inside one Gaussian training run (``ViewProtocol``: the
  held-out views join training once no decision needs them).
"""
