#include "frame.h"

#include <string.h>

#include "crc16.h"
#include "fixed.h"

void line_rx_reset(line_rx_t *rx)
{
    rx->len = 0;
    rx->buf[0] = '\0';
}

line_status_t line_rx_push(line_rx_t *rx, uint8_t byte)
{
    if (byte == '\n') {
        if (rx->overflowed) { /* the tail of a line already reported as too long */
            rx->overflowed = false;
            line_rx_reset(rx);
            return LINE_NONE;
        }
        rx->buf[rx->len] = '\0';
        return LINE_READY;
    }
    if (rx->overflowed) {
        return LINE_NONE;
    }
    /* FRAME_MAX_BYTES counts the '\n', so a body+checksum may be one byte shorter. */
    if (rx->len >= FRAME_MAX_BYTES - 1) {
        rx->overflowed = true;
        line_rx_reset(rx);
        return LINE_OVERFLOW;
    }
    rx->buf[rx->len++] = (char)byte;
    return LINE_NONE;
}

static bool is_word(const char *s) /* [A-Z][A-Z0-9_]* */
{
    if (!(*s >= 'A' && *s <= 'Z')) {
        return false;
    }
    for (s++; *s; s++) {
        if (!((*s >= 'A' && *s <= 'Z') || (*s >= '0' && *s <= '9') || *s == '_')) {
            return false;
        }
    }
    return true;
}

static bool is_key(const char *s, size_t n) /* [a-z][a-z0-9_]* */
{
    if (n == 0 || !(s[0] >= 'a' && s[0] <= 'z')) {
        return false;
    }
    for (size_t i = 1; i < n; i++) {
        char c = s[i];
        if (!((c >= 'a' && c <= 'z') || (c >= '0' && c <= '9') || c == '_')) {
            return false;
        }
    }
    return true;
}

static int hexval(char c)
{
    if (c >= '0' && c <= '9') {
        return c - '0';
    }
    if (c >= 'A' && c <= 'F') {
        return c - 'A' + 10;
    }
    return -1; /* lower case is not accepted: the checksum is upper-case hex */
}

const char *frame_decode_command(const char *line, size_t len, command_t *out)
{
    if (len > 0 && line[len - 1] == '\r') {
        len--; /* CRLF from a terminal-minded peer */
    }
    if (len + 1 > FRAME_MAX_BYTES) {
        return "line too long";
    }
    size_t star = len;
    for (size_t i = len; i > 0; i--) {
        if (line[i - 1] == '*') {
            star = i - 1;
            break;
        }
    }
    if (star == len) {
        return "no checksum";
    }
    for (size_t i = 0; i < len; i++) {
        unsigned char c = (unsigned char)line[i];
        if (c > 0x7E) {
            return "not ASCII";
        }
    }
    if (len - star - 1 != 4) {
        return "checksum is not 4 hex digits";
    }
    unsigned crc = 0;
    for (int i = 0; i < 4; i++) {
        int v = hexval(line[star + 1 + (size_t)i]);
        if (v < 0) {
            return "checksum is not 4 hex digits";
        }
        crc = (crc << 4) | (unsigned)v;
    }
    if (crc != crc16_ccitt_false(line, star)) {
        return "bad checksum";
    }
    if (star == 0) {
        return "empty body";
    }
    for (size_t i = 0; i < star; i++) {
        if ((unsigned char)line[i] < 0x20) {
            return "control character";
        }
    }
    memcpy(out->body, line, star);
    out->body[star] = '\0';
    /* split on single spaces; an empty token (double or trailing space) is malformed */
    char *tokens[FRAME_MAX_FIELDS + 2];
    int nt = 0;
    char *p = out->body;
    for (;;) {
        if (nt == FRAME_MAX_FIELDS + 2) {
            return "too many fields";
        }
        tokens[nt++] = p;
        char *sp = strchr(p, ' ');
        if (!sp) {
            break;
        }
        *sp = '\0';
        p = sp + 1;
    }
    for (int i = 0; i < nt; i++) {
        if (tokens[i][0] == '\0') {
            return "empty token";
        }
    }
    if (nt < 2) {
        return "no sequence number and name";
    }
    const char *head = tokens[0];
    if (head[0] == '!') {
        return "an event sent to the device";
    }
    if (strcmp(tokens[1], "OK") == 0 || strcmp(tokens[1], "ERR") == 0) {
        return "a reply sent to the device";
    }
    size_t hl = strlen(head);
    if (hl > 5 || (head[0] == '0' && hl > 1)) {
        return "bad sequence number";
    }
    unsigned long seq = 0;
    for (size_t i = 0; i < hl; i++) {
        if (head[i] < '0' || head[i] > '9') {
            return "bad sequence number";
        }
        seq = seq * 10 + (unsigned long)(head[i] - '0');
    }
    if (seq > 65535) {
        return "bad sequence number";
    }
    if (!is_word(tokens[1])) {
        return "bad command name";
    }
    out->seq = (uint16_t)seq;
    out->name = tokens[1];
    out->n_fields = 0;
    for (int i = 2; i < nt; i++) {
        char *eq = strchr(tokens[i], '=');
        if (!eq || !is_key(tokens[i], (size_t)(eq - tokens[i])) || eq[1] == '\0') {
            return "bad field";
        }
        *eq = '\0';
        for (int j = 0; j < out->n_fields; j++) {
            if (strcmp(out->fields[j].key, tokens[i]) == 0) {
                return "duplicate field";
            }
        }
        out->fields[out->n_fields].key = tokens[i];
        out->fields[out->n_fields].value = eq + 1;
        out->n_fields++;
    }
    return NULL;
}

const char *command_field(const command_t *cmd, const char *key)
{
    for (int i = 0; i < cmd->n_fields; i++) {
        if (strcmp(cmd->fields[i].key, key) == 0) {
            return cmd->fields[i].value;
        }
    }
    return NULL;
}

/* ---- sending ---- */

static void put(frame_tx_t *f, const char *s, size_t n)
{
    /* keep 6 bytes for "*CCCC\n" */
    if (f->overflow || f->len + n + 6 > FRAME_MAX_BYTES) {
        f->overflow = true;
        return;
    }
    memcpy(f->buf + f->len, s, n);
    f->len += n;
}

static void put_s(frame_tx_t *f, const char *s)
{
    put(f, s, strlen(s));
}

static void put_u(frame_tx_t *f, uint32_t v)
{
    char d[12];
    int n = 0;
    do {
        d[n++] = (char)('0' + v % 10);
        v /= 10;
    } while (v);
    char o[12];
    for (int i = 0; i < n; i++) {
        o[i] = d[n - 1 - i];
    }
    put(f, o, (size_t)n);
}

void frame_begin_reply(frame_tx_t *f, uint16_t seq, bool ok)
{
    f->len = 0;
    f->overflow = false;
    f->reply = true;
    f->seq = seq;
    put_u(f, seq);
    put_s(f, ok ? " OK" : " ERR");
}

void frame_begin_event(frame_tx_t *f, uint16_t number, const char *name)
{
    f->len = 0;
    f->overflow = false;
    f->reply = false;
    put_s(f, "!");
    put_u(f, number);
    put_s(f, " ");
    put_s(f, name);
}

void frame_add_text(frame_tx_t *f, const char *text)
{
    put_s(f, " ");
    for (; *text; text++) {
        char c = (*text >= ' ' && *text <= '~' && *text != '*') ? *text : '?';
        put(f, &c, 1);
    }
}

void frame_add_str(frame_tx_t *f, const char *key, const char *value)
{
    put_s(f, " ");
    put_s(f, key);
    put_s(f, "=");
    put_s(f, value);
}

void frame_add_int(frame_tx_t *f, const char *key, int64_t value)
{
    frame_add_micro(f, key, value * FX_ONE);
}

void frame_add_micro(frame_tx_t *f, const char *key, int64_t micro)
{
    char num[32];
    fx_format(num, sizeof num, micro);
    frame_add_str(f, key, num);
}

void frame_add_micro_list(frame_tx_t *f, const char *key, const int64_t *micro, int n)
{
    char num[32];
    put_s(f, " ");
    put_s(f, key);
    put_s(f, "=");
    for (int i = 0; i < n; i++) {
        if (i) {
            put_s(f, ",");
        }
        size_t k = fx_format(num, sizeof num, micro[i]);
        put(f, num, k);
    }
}

size_t frame_finish(frame_tx_t *f)
{
    static const char hex[] = "0123456789ABCDEF";
    if (f->overflow) {
        return 0;
    }
    uint16_t crc = crc16_ccitt_false(f->buf, f->len);
    char tail[6] = {'*', hex[(crc >> 12) & 15], hex[(crc >> 8) & 15], hex[(crc >> 4) & 15],
                    hex[crc & 15], '\n'};
    memcpy(f->buf + f->len, tail, 6);
    f->len += 6;
    f->buf[f->len] = '\0';
    return f->len;
}
