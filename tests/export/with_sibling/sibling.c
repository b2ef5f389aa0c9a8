/* The second library of the test FMU: the decay rate lives here. */
__attribute__((visibility("default"))) double sibling_rate(void) { return 0.5; }
