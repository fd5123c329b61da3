/* The constants of docs/serial-protocol.md (wire protocol v1). */
#ifndef CLOTHD_FW_PROTOCOL_H
#define CLOTHD_FW_PROTOCOL_H

#define PROTOCOL_VERSION 1

/* Message types: host -> controller */
#define MSG_HELLO 0x01
#define MSG_COMMAND 0x02
#define MSG_ESTOP 0x03
#define MSG_ESTOP_CLEAR 0x04
#define MSG_PING 0x05
/* controller -> host */
#define MSG_ACK 0x80
#define MSG_HELLO_ACK 0x81
#define MSG_NACK 0x82
#define MSG_FAULT 0x90

/* ACK flags */
#define FLAG_ESTOP 0x01
#define FLAG_WATCHDOG 0x02

/* NACK reasons */
#define NACK_ESTOPPED 1
#define NACK_BAD_LENGTH 2
#define NACK_UNKNOWN_TYPE 3
#define NACK_BAD_VERSION 4

/* FAULT codes */
#define FAULT_WATCHDOG 1
#define FAULT_STALL 2
#define FAULT_OVERTEMP 3
#define FAULT_ESTOP_INPUT 4
#define FAULT_MODULE_BOARD 0xFFFF /* the fault concerns the whole board, not one module */

/* COMMAND payload units: speed in 1e-4 m/s, heading in 1e-4 rad, both int16 little-endian. */
#define SPEED_UNIT_M_S 1e-4f
#define HEADING_UNIT_RAD 1e-4f

/* No valid frame for this long after the first COMMAND: every module is stopped. */
#define WATCHDOG_TIMEOUT_MS 250u

#endif
