/* arena_proto.c: see arena_proto.h. */
#include "arena_proto.h"

uint16_t ap_crc16(const uint8_t *data, size_t len) {
  uint16_t crc = 0xFFFF;
  for (size_t i = 0; i < len; i++) {
    crc ^= (uint16_t)data[i] << 8;
    for (uint8_t b = 0; b < 8; b++) {
      crc = (crc & 0x8000) ? (uint16_t)((crc << 1) ^ 0x1021) : (uint16_t)(crc << 1);
    }
  }
  return crc;
}

size_t ap_cobs_encode(const uint8_t *in, size_t len, uint8_t *out) {
  size_t code_at = 0, o = 1;
  uint8_t code = 1;
  for (size_t i = 0; i < len; i++) {
    if (in[i] == 0) {
      out[code_at] = code;
      code_at = o++;
      code = 1;
    } else {
      out[o++] = in[i];
      if (++code == 0xFF) {
        out[code_at] = code;
        code_at = o++;
        code = 1;
      }
    }
  }
  out[code_at] = code;
  return o;
}

size_t ap_cobs_decode(const uint8_t *in, size_t len, uint8_t *out) {
  size_t i = 0, o = 0;
  while (i < len) {
    uint8_t code = in[i];
    if (code == 0 || i + code > len) return (size_t)-1;
    for (uint8_t k = 1; k < code; k++) {
      if (in[i + k] == 0) return (size_t)-1;
      out[o++] = in[i + k];
    }
    i += code;
    if (code != 0xFF && i < len) out[o++] = 0;
  }
  return o;
}

size_t ap_encode_frame(uint8_t type, uint16_t seq, uint32_t time_us,
                       const uint8_t *body, size_t body_len, uint8_t *out) {
  uint8_t packet[AP_MAX_PACKET];
  if (body_len + AP_HEADER_SIZE + 2 > AP_MAX_PACKET) return 0;
  packet[0] = AP_VERSION;
  packet[1] = type;
  ap_put_u16(packet + 2, seq);
  ap_put_u32(packet + 4, time_us);
  for (size_t i = 0; i < body_len; i++) packet[AP_HEADER_SIZE + i] = body[i];
  size_t n = AP_HEADER_SIZE + body_len;
  ap_put_u16(packet + n, ap_crc16(packet, n));
  n += 2;
  size_t m = ap_cobs_encode(packet, n, out);
  out[m++] = 0;
  return m;
}

void ap_decoder_init(ap_decoder *dec) {
  dec->raw_len = 0;
  dec->len = 0;
  dec->overflow = 0;
  dec->frames = dec->crc_errors = dec->frame_errors = dec->version_errors = 0;
}

int ap_decoder_feed(ap_decoder *dec, uint8_t byte) {
  if (byte != 0) {
    if (dec->raw_len < sizeof dec->raw) {
      dec->raw[dec->raw_len++] = byte;
    } else {
      dec->overflow = 1;
    }
    return AP_NONE;
  }
  size_t raw_len = dec->raw_len;
  uint8_t overflow = dec->overflow;
  dec->raw_len = 0;
  dec->overflow = 0;
  if (raw_len == 0 && !overflow) return AP_NONE; /* resync delimiter */
  if (overflow) { dec->frame_errors++; return AP_BAD_FRAME; }
  size_t n = ap_cobs_decode(dec->raw, raw_len, dec->packet);
  if (n == (size_t)-1 || n < AP_HEADER_SIZE + 2 || n > AP_MAX_PACKET) {
    dec->frame_errors++;
    return AP_BAD_FRAME;
  }
  uint16_t crc = (uint16_t)(dec->packet[n - 2] | (dec->packet[n - 1] << 8));
  if (ap_crc16(dec->packet, n - 2) != crc) { dec->crc_errors++; return AP_BAD_CRC; }
  if (dec->packet[0] != AP_VERSION) { dec->version_errors++; return AP_BAD_VERSION; }
  dec->len = n;
  dec->frames++;
  return AP_FRAME;
}
