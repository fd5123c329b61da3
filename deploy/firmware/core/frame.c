#include "frame.h"

#include "cobs.h"
#include "crc16.h"

/* The biggest frame this firmware sends: HELLO_ACK or FAULT with a short text. */
#define FRAME_ENCODE_SCRATCH_BYTES 256

void frame_rx_init(frame_rx *rx)
{
    rx->wire_len = 0;
    rx->overflowed = false;
}

static uint16_t read_u16_le(const uint8_t *p)
{
    return (uint16_t)(p[0] | (p[1] << 8));
}

static frame_result decode_packet(frame_rx *rx, frame_msg *msg)
{
    size_t len = 0;
    if (!cobs_decode(rx->wire, rx->wire_len, rx->decoded, sizeof rx->decoded, &len)) {
        return FRAME_INVALID;
    }
    if (len < FRAME_MIN_DECODED_BYTES) {
        return FRAME_INVALID;
    }
    size_t body_len = len - FRAME_CRC_BYTES;
    if (crc16_ccitt(rx->decoded, body_len) != read_u16_le(rx->decoded + body_len)) {
        return FRAME_INVALID;
    }
    msg->type = rx->decoded[0];
    msg->seq = read_u16_le(rx->decoded + 1);
    msg->payload = rx->decoded + FRAME_HEADER_BYTES;
    msg->payload_len = body_len - FRAME_HEADER_BYTES;
    return FRAME_OK;
}

static frame_result end_of_packet(frame_rx *rx, frame_msg *msg)
{
    frame_result result = FRAME_NONE;
    /* An overlong run was already counted when it overflowed; an empty packet is just two delimiters
     * (a sender may flush the line with one), not an error. */
    if (!rx->overflowed && rx->wire_len > 0) {
        result = decode_packet(rx, msg);
    }
    frame_rx_init(rx);
    return result;
}

frame_result frame_rx_push(frame_rx *rx, uint8_t byte, frame_msg *msg)
{
    if (byte == 0) {
        return end_of_packet(rx, msg);
    }
    if (rx->overflowed) {
        return FRAME_NONE;
    }
    if (rx->wire_len == sizeof rx->wire) {
        /* Drop the whole run up to the next delimiter: the next frame starts after it. */
        rx->overflowed = true;
        return FRAME_INVALID;
    }
    rx->wire[rx->wire_len++] = byte;
    return FRAME_NONE;
}

size_t frame_encode(uint8_t type, uint16_t seq, const uint8_t *payload, size_t payload_len, uint8_t *out,
                    size_t out_cap)
{
    uint8_t body[FRAME_ENCODE_SCRATCH_BYTES];
    size_t body_len = FRAME_HEADER_BYTES + payload_len;
    if (body_len + FRAME_CRC_BYTES > sizeof body) {
        return 0;
    }
    body[0] = type;
    body[1] = (uint8_t)(seq & 0xFF);
    body[2] = (uint8_t)(seq >> 8);
    for (size_t i = 0; i < payload_len; i++) {
        body[FRAME_HEADER_BYTES + i] = payload[i];
    }
    uint16_t crc = crc16_ccitt(body, body_len);
    body[body_len++] = (uint8_t)(crc & 0xFF);
    body[body_len++] = (uint8_t)(crc >> 8);
    if (out_cap < 1) {
        return 0;
    }
    size_t wire_len = cobs_encode(body, body_len, out, out_cap - 1);
    if (wire_len == 0) {
        return 0;
    }
    out[wire_len] = 0;
    return wire_len + 1;
}
