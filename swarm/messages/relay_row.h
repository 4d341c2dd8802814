/* A row of BeaconRelayWire.data (swarm.messages.wire): one relayed beacon, float64.
 *
 * The one statement of its columns: swarm.messages._wire exports them (RELAY_FIELDS, which
 * the wire reads) and swarm.agent._exchange reads rows by them (nearby).
 */
#ifndef SWARM_RELAY_ROW_H
#define SWARM_RELAY_ROW_H

enum {
    RELAY_POSITION = 0,    /* the beacon's position (3) [m, W] */
    RELAY_VELOCITY = 3,    /* its velocity (3) [m/s, W] */
    RELAY_SAMPLE_AGE = 6,  /* the age of its position sample when the drone sent it [s] */
    RELAY_HELD = 7,        /* how long the world had held it when the relay left [s] */
    RELAY_WIDTH = 8
};

#endif
