"""Design advisor (``nanostage design``): the seed's Chapter 6 and Sec. 3.3-3.4 guidelines as a tool.

Friction isolator (Sec. 6.3.2, 6.4.2): :mod:`.sweep` lumps a preset into the Fig. 6.2 model and
simulates and analyses its FI (``k_fi``, ``c_fi``) grid; :mod:`.advice` applies the seed's rule to
the sweep and recommends a design. VAN (Sec. 3.3, 3.4.3): :mod:`.van` checks the piezo power and
the flexure fatigue. :mod:`.report` writes ``design.md``, ``design.json`` and the PNG plots;
:mod:`.cli` is the command line.
"""
