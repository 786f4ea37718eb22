"""The centralized learner: critic, actor, update rules, the month loop and its run files.

- :mod:`~mpcrl_lite.learning.lstd`: value and compatible features, LSTD (the critic);
- :mod:`~mpcrl_lite.learning.dpg`: the deterministic policy gradient (eq. 13) and the update;
- :mod:`~mpcrl_lite.learning.update_rules`: one class per update rule (SGD, Adam, natural);
- :mod:`~mpcrl_lite.learning.rollout_gradient`: the policy gradient from replayed days (the
  measured slope of the cost-to-go, what the critic should estimate);
- :mod:`~mpcrl_lite.learning.pathwise`: the exact derivative of a simulated month's cost in
  theta (the gradient of the ``'pathwise'`` learner, an extension);
- :mod:`~mpcrl_lite.learning.learner`: the learning step and the month loop both learners
  share, with checkpoints and resume;
- :mod:`~mpcrl_lite.learning.rundir`: the durable run directory;
- :mod:`~mpcrl_lite.learning.history`: a run's results as data;
- :mod:`~mpcrl_lite.learning.experiment`: the centralized learning experiment;
- :mod:`~mpcrl_lite.learning.eval_worker`: its evaluations in a second process, beside the
  months.

May import: :mod:`mpcrl_lite.sim` and below.
"""
