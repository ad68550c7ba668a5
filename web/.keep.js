/* PhysMotion front-end extensions (the force/torque picker lands here). */
