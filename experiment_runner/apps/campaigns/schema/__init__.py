"""The campaign file's ``test`` schemas: one module per campaign kind, named as the kind.

A campaign kind (``test: {kind: NAME}``) has its schema -- the pydantic class that validates
the ``test`` mapping, knows the kind's conditions, metrics and reference -- in
``schema/NAME.py``, and its behaviour (run, results, report, plots) in the object
``experiment_runner.apps.campaigns.kinds.KINDS[NAME]``:

==========================  ==========================================  ===========================
kind                        schema                                      behaviour
==========================  ==========================================  ===========================
``point_to_point``          ``schema.point_to_point.PointToPointTest``  ``trial_kinds.POINT_TO_POINT``
``circle``                  ``schema.circle.CircleTest``                ``trial_kinds.CIRCLE``
``frequency_response``      ``schema.frequency_response``               ``frequency_response``
                            ``.FrequencyResponseTest``                  ``.FREQUENCY_RESPONSE``
==========================  ==========================================  ===========================

``schema.common`` holds what they share (:class:`~experiment_runner.apps.campaigns.schema.common.Condition`,
the identifier type, length labels); the kind modules do not import each other (``.importlinter``).
The campaign model (:mod:`experiment_runner.apps.campaigns.spec`) assembles the kinds' schemas
into its ``Test`` union; ``test/test_campaign_files.py`` checks that every kind in ``KINDS`` has
its schema here, in the module of its name, and that the union holds exactly those.
"""
